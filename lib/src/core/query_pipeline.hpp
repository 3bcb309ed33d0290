// The kind of a host-array query, as data for Index::run_query (query_pipeline.cpp): what a kNN
// query (KnnKind, knn.cpp) and a radius query (RadiusKind, radius.cpp) do differently. The driver
// calls, in order: check, begin, then per chunk of at most chunk_rows(n) queries (gathered in
// dispatch order into the device's buffer) search_chunk, or once search_host for a host method;
// then finish and answer_exactly over the suspect rows.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "blockhash_cl/knn.hpp"

namespace bhcl {

class Index::QueryKind {
 public:
  explicit QueryKind(const Index& ix) : ix_(ix) {}
  virtual ~QueryKind() = default;
  QueryKind(const QueryKind&) = delete;
  QueryKind& operator=(const QueryKind&) = delete;

  virtual const char* name() const = 0;  // the entry point, for messages
  virtual const DispatchParams& dispatch() const = 0;
  // Rows of k entries (kNN) or 0 (radius: variable slices); also the warm-up's kernel variant.
  virtual std::size_t row_k() const = 0;
  virtual int kernel_variant() const = 0;  // the warm-up key: kmax, or 0 for the radius kernels
  // The parameters, and the memory n queries need before anything is allocated (`copies` of the
  // rows where the Hilbert order holds them twice). Throws bhcl::Error.
  virtual void check(std::size_t n, int copies) const = 0;
  virtual void begin(std::size_t n) = 0;  // the output sized for n rows
  // Queries per host chunk: the device memory of one call is bounded by what they need.
  virtual std::size_t chunk_rows(std::size_t n) const = 0;
  // Zero-count launches of each pass (the compile), on the library's warm queue.
  virtual void warm_launch(const QueryBuffers& b, std::size_t local) const = 0;
  // Device methods: queries [first, first + m) of the call (dispatch order; order[i], or i where
  // order is null, is the caller's row of dispatch row i) are in b.q in the structure's
  // coordinates: dispatch at most `per` per kernel, fetch the rows, note the suspect ones.
  virtual void search_chunk(QueryBuffers& b, std::size_t first, std::size_t m, const std::size_t* order,
                            std::size_t per, std::size_t local, const float* caller_queries, QueryStats& st,
                            std::vector<std::size_t>& suspects) = 0;
  // Host methods: every query, in dispatch order and the structure's coordinates.
  virtual void search_host(const float* queries, std::size_t n, const std::size_t* order,
                           const float* caller_queries, QueryStats& st, std::vector<std::size_t>& suspects) = 0;
  // The rows in the caller's order and scale; suspect rows (caller rows) still to be re-answered.
  virtual void finish(const std::size_t* order, const float* caller_queries, QueryStats& st,
                      std::vector<std::size_t>& suspects) = 0;
  // Exact methods: rows (ascending) answered again in double over the caller's points.
  virtual void answer_exactly(const float* caller_queries, const std::vector<std::size_t>& rows) = 0;

 protected:
  using Candidate = std::pair<double, std::int32_t>;  // (true squared distance, id)
  // Exact methods whose rows the double-precision fallback can re-answer.
  bool checks_rows() const { return ix_.exact() && !ix_.caller_points_.empty(); }
  int scale_exponent() const { return ix_.scale_exp_; }
  // An entry whose float distance (the structure's coordinates) the ranking cannot vouch for.
  bool entry_suspect(const float* q, std::int32_t id, float d) const;
  // The points within r2 (true squared distance, double) of q in (distance, id) order: the k
  // nearest, or all of them for k = 0.
  void exact_candidates(const float* q, double r2, std::size_t k, std::vector<Candidate>& best) const;
  const Index& ix_;
};

namespace detail {
// Below this a squared distance in the structure's coordinates may have lost precision (its
// components' squares underflow); the float ranking is then not vouched for.
float trusted_min_distance();
// A double squared distance as the contract reports it: rounded to float, +inf above FLT_MAX.
float to_float_or_inf(double d);
inline bool finite_query(const float* q) { return std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]); }

// Host buffers a CPU device reads and writes in place (zero-copy: PoCL's kernels use the host
// memory itself); a GPU gets device memory and copies.
cl::Buffer io_buffer(const Runtime& rt, bool host_visible, std::size_t bytes, const char* what);

// A mapped region of a buffer, unmapped when done (also on an exception). blocking false: the
// pointer is valid once the queue has run the map (one wait for several maps, not one each).
class Mapped {
 public:
  Mapped(const cl::CommandQueue& q, const cl::Buffer& b, cl_map_flags flags, std::size_t bytes, const char* what,
         bool blocking = true);
  ~Mapped() {
    if (ptr_) q_.enqueueUnmapMemObject(b_, ptr_);
  }
  Mapped(const Mapped&) = delete;
  Mapped& operator=(const Mapped&) = delete;
  void unmap(const char* what);
  template <typename T>
  T* as() const { return static_cast<T*>(ptr_); }

 private:
  const cl::CommandQueue& q_;
  const cl::Buffer& b_;
  void* ptr_ = nullptr;
};
}  // namespace detail

}  // namespace bhcl
