// Helpers the translation units of blockhash_cl._core share (bindings.cpp, distributed_bindings.cpp).
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl_py {

namespace py = pybind11;

// A numpy array that owns `v` (moved to the heap, freed with the array): the results leave the
// library without a copy.
template <typename T>
inline py::array_t<T> to_numpy(std::vector<T>&& v, std::vector<py::ssize_t> shape) {
  auto* heap = new std::vector<T>(std::move(v));
  py::capsule owner(heap, [](void* p) { delete static_cast<std::vector<T>*>(p); });
  return py::array_t<T>(std::move(shape), heap->data(), owner);
}

// The (n, 3) float32 C-contiguous array the Python layer prepared; checked again here because
// _core is importable on its own.
inline std::size_t rows_of(const py::array_t<float, py::array::c_style>& a, const char* what) {
  if (a.ndim() != 2 || a.shape(1) != 3)
    throw py::value_error(std::string(what) + " must have shape (n, 3)");
  return static_cast<std::size_t>(a.shape(0));
}

inline py::dict stats_dict(const bhcl::QueryStats& s) {
  py::dict o;
  s.for_each_field([&](const char* name, auto value) { o[name] = value; });
  return o;
}

}  // namespace bhcl_py
