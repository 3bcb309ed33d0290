// blockhash_cl._core's binding of bhcl::DistributedIndex (issue 40, part 3): compiled into _core
// when the build found MPI (python/CMakeLists.txt: the target blockhash_cl_distributed exists).
//
// The communicator crosses as its Fortran handle (mpi4py's Comm.py2f(), an int), turned back
// into an MPI_Comm here by MPI_Comm_f2c: nothing of mpi4py is needed at build time, and the
// package imports and runs without it (world() then initialises MPI itself). mpi4py and this
// module load the same libmpi, so a handle means the same communicator on both sides.
//
// Every call here is collective over the communicator, as DistributedIndex's are; the Python
// layer (python/blockhash_cl/_distributed.py) agrees its own checks over the ranks first (agree),
// so that a bad argument on one rank raises on every rank instead of leaving the others waiting.
#include <mpi.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "blockhash_cl/distributed.hpp"
#include "blockhash_cl/error.hpp"
#include "distributed/agreement.hpp"
#include "py_common.hpp"

namespace py = pybind11;
using bhcl_py::rows_of;
using bhcl_py::stats_dict;
using bhcl_py::to_numpy;

namespace {

// Whether this module called MPI_Init (no mpi4py): then finalize() ends MPI at exit.
bool g_we_initialised = false;

bool mpi_usable() {
  int init = 0, fin = 0;
  MPI_Initialized(&init);
  MPI_Finalized(&fin);
  return init && !fin;
}

void require_mpi(const char* call) {
  if (!mpi_usable())
    throw bhcl::Error(std::string(call) + ": MPI is not initialised (or already finalised): pass an mpi4py "
                      "communicator, or comm=None for MPI_COMM_WORLD");
}

// MPI_COMM_WORLD's handle, initialising MPI first where nobody has (no mpi4py): MPI_THREAD_FUNNELED,
// as the bhcl tool asks (the library calls MPI from the calling thread only).
int world() {
  int init = 0, fin = 0;
  MPI_Initialized(&init);
  MPI_Finalized(&fin);
  if (fin) throw bhcl::Error("DistributedIndex: MPI was finalised already in this process");
  if (!init) {
    int provided = 0;
    if (MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided) != MPI_SUCCESS)
      throw bhcl::Error("DistributedIndex: MPI_Init_thread failed");
    g_we_initialised = true;
  }
  return static_cast<int>(MPI_Comm_c2f(MPI_COMM_WORLD));
}

// At exit (the package registers it): MPI_Finalize where world() initialised MPI.
void finalize() {
  if (g_we_initialised && mpi_usable()) MPI_Finalize();
  g_we_initialised = false;
}

MPI_Comm comm_of(int handle, const char* call) {
  require_mpi(call);
  MPI_Comm c = MPI_Comm_f2c(static_cast<MPI_Fint>(handle));
  if (c == MPI_COMM_NULL) throw bhcl::Error(std::string(call) + ": the communicator is MPI_COMM_NULL");
  return c;
}

// The Python layer's own duplicate of the caller's communicator (its agreements never meet the
// caller's messages), with the index's deadline; freed unless MPI has ended first.
class Comm {
 public:
  Comm(int handle, double deadline_s) {
    MPI_Comm c = comm_of(handle, "DistributedIndex");
    MPI_Comm_dup(c, &comm_);
    if (deadline_s >= 0 && std::isfinite(deadline_s)) bhcl::distributed::set_deadline(comm_, deadline_s);
    MPI_Comm_rank(comm_, &rank_);
    MPI_Comm_size(comm_, &size_);
  }
  ~Comm() {
    if (mpi_usable() && comm_ != MPI_COMM_NULL) MPI_Comm_free(&comm_);
  }
  Comm(const Comm&) = delete;
  Comm& operator=(const Comm&) = delete;

  MPI_Comm get() const { return comm_; }
  int rank() const { return rank_; }
  int size() const { return size_; }
  // Collective: Error on every rank when any rank's message is non-empty (the first's, named),
  // or when the ranks are not in the same call (`what` differs: one rank in add, another in
  // query), which would otherwise pair one call's messages with another's and hang or corrupt.
  void agree(const std::string& local_error, const std::string& what) const {
    require_mpi(what.c_str());
    py::gil_scoped_release nogil;
    bhcl::mpi_agree(comm_, local_error, what);
    agree_call(what);
  }
  // Collective: the element-wise minimum of lo and maximum of hi over the ranks (a box of all
  // the ranks' points; +inf / -inf for a rank with none).
  py::tuple box(std::vector<double> lo, std::vector<double> hi) const {
    if (lo.size() != 3 || hi.size() != 3) throw py::value_error("box: lo and hi need 3 values");
    require_mpi("box");
    std::vector<double> glo(3), ghi(3);
    {
      py::gil_scoped_release nogil;
      MPI_Allreduce(lo.data(), glo.data(), 3, MPI_DOUBLE, MPI_MIN, comm_);
      MPI_Allreduce(hi.data(), ghi.data(), 3, MPI_DOUBLE, MPI_MAX, comm_);
    }
    return py::make_tuple(glo, ghi);
  }

 private:
  // One allreduce of the call's name hash (its minimum and, as ~h, its maximum); only when they
  // differ, the names themselves are gathered so that the message says which rank is where.
  void agree_call(const std::string& what) const {
    const std::uint64_t h = std::hash<std::string>{}(what);
    std::uint64_t mine[2] = {h, ~h}, all[2] = {0, 0};
    MPI_Allreduce(mine, all, 2, MPI_UINT64_T, MPI_MIN, comm_);
    if (all[0] == ~all[1]) return;
    constexpr int kName = 64;
    std::vector<char> name(kName, '\0'), names(static_cast<std::size_t>(kName) * size_, '\0');
    what.copy(name.data(), kName - 1);
    MPI_Allgather(name.data(), kName, MPI_CHAR, names.data(), kName, MPI_CHAR, comm_);
    std::string msg = "the ranks are not in the same collective call (every rank makes the same calls in the "
                      "same order):";
    for (int r = 0; r < size_; ++r)
      msg += std::string(r ? "," : "") + " rank " + std::to_string(r) + " in " + (names.data() + r * kName);
    throw bhcl::Error(what + ": " + msg);
  }

  MPI_Comm comm_ = MPI_COMM_NULL;
  int rank_ = 0, size_ = 1;
};

// What a call did beyond QueryStats: DistributedQueryStats, its per-query arrays as numpy.
void add_distributed_stats(py::dict& o, bhcl::DistributedQueryStats&& ds) {
  o["multi_rank_queries"] = ds.multi_rank_queries;
  o["owner_sent"] = ds.owner_sent;
  o["owner_received"] = ds.owner_received;
  o["extra_sent"] = ds.extra_sent;
  o["extra_received"] = ds.extra_received;
  o["reanswered"] = ds.reanswered;
  o["answered"] = ds.answered;
  o["bytes_sent"] = ds.bytes_sent;
  o["bytes_received"] = ds.bytes_received;
  o["phase1_s"] = ds.phase1_s;
  o["phase2_s"] = ds.phase2_s;
  const auto n = static_cast<py::ssize_t>(ds.owner.size());
  o["owner"] = to_numpy(std::move(ds.owner), {n});
  o["ranks_visited"] = to_numpy(std::move(ds.ranks_visited), {n});
}

std::unique_ptr<bhcl::DistributedIndex> build(const Comm& comm, std::shared_ptr<bhcl::Runtime> runtime,
                                              const py::array_t<float, py::array::c_style>& points,
                                              const std::string& method, const bhcl::MethodOptions& options,
                                              int boxes_per_rank, float border_factor, double deadline_s,
                                              std::int64_t id_base) {
  if (!runtime) throw py::value_error("DistributedIndex: runtime is None");
  const std::size_t n = rows_of(points, "points");
  bhcl::DistributedBuildParams p;
  p.method = method;
  p.options = options;
  p.boxes_per_rank = boxes_per_rank;
  p.border_factor = border_factor;
  p.deadline_s = deadline_s;
  p.id_base = id_base;
  require_mpi("DistributedIndex");
  py::gil_scoped_release nogil;
  return std::make_unique<bhcl::DistributedIndex>(comm.get(), std::move(runtime), points.data(), n, p);
}

// kNN: (dist2 (n, k) float32, ids (n, k) int64 global ids, counts (n,) int32, stats dict).
py::tuple knn(const bhcl::DistributedIndex& index, const py::array_t<float, py::array::c_style>& queries,
              const bhcl::SearchParams& params) {
  const std::size_t n = rows_of(queries, "queries");
  require_mpi("DistributedIndex.query");
  bhcl::KnnResult64 r;
  bhcl::DistributedQueryStats ds;
  bhcl::QueryStats st;
  {
    py::gil_scoped_release nogil;
    st = index.query(queries.data(), n, params, r, &ds);
  }
  const auto rows = static_cast<py::ssize_t>(n), k = static_cast<py::ssize_t>(params.k);
  py::dict stats = stats_dict(st);
  add_distributed_stats(stats, std::move(ds));
  return py::make_tuple(to_numpy(std::move(r.dist2), {rows, k}), to_numpy(std::move(r.ids), {rows, k}),
                        to_numpy(std::move(r.counts), {rows}), stats);
}

// Radius search: (offsets (n + 1,) int64, dist2 float32, ids int64, found (n,) int64, stats).
py::tuple radius(const bhcl::DistributedIndex& index, const py::array_t<float, py::array::c_style>& queries,
                 float r, const bhcl::RadiusParams& params) {
  const std::size_t n = rows_of(queries, "queries");
  require_mpi("DistributedIndex.radius_search");
  bhcl::RadiusResult64 out;
  bhcl::DistributedQueryStats ds;
  bhcl::QueryStats st;
  {
    py::gil_scoped_release nogil;
    st = index.radius_search(queries.data(), n, r, params, out, &ds);
  }
  const auto total = static_cast<py::ssize_t>(out.total()), rows = static_cast<py::ssize_t>(n);
  py::dict stats = stats_dict(st);
  stats["truncated_queries"] = out.truncated_queries;
  stats["results"] = out.total();
  add_distributed_stats(stats, std::move(ds));
  return py::make_tuple(to_numpy(std::move(out.offsets), {rows + 1}), to_numpy(std::move(out.dist2), {total}),
                        to_numpy(std::move(out.ids), {total}), to_numpy(std::move(out.found), {rows}), stats);
}

// Collective updates (DistributedIndex::insert / remove), the GIL released while they run.
py::dict update_stats_dict(const bhcl::DistributedUpdateStats& u) {
  py::dict o;
  o["n_global"] = u.n_global;
  o["n_input"] = u.n_input;
  o["applied"] = u.applied;
  o["sent"] = u.sent;
  o["bytes_sent"] = u.bytes_sent;
  o["bytes_received"] = u.bytes_received;
  o["route_s"] = u.route_s;
  o["local_s"] = u.local_s;
  o["boxes_s"] = u.boxes_s;
  o["wall_s"] = u.wall_s;
  return o;
}

// (the global id of this rank's first point, the call's stats).
py::tuple insert_points(bhcl::DistributedIndex& index, const py::array_t<float, py::array::c_style>& points) {
  const std::size_t n = rows_of(points, "points");
  require_mpi("DistributedIndex.add");
  bhcl::DistributedUpdateStats us;
  std::int64_t first = 0;
  {
    py::gil_scoped_release nogil;
    first = index.insert(points.data(), n, &us);
  }
  return py::make_tuple(first, update_stats_dict(us));
}

py::dict remove_ids(bhcl::DistributedIndex& index, const py::array_t<std::int64_t, py::array::c_style>& ids) {
  if (ids.ndim() != 1)
    throw bhcl::Error("DistributedIndex.remove: ids must be a 1-D array, got " + std::to_string(ids.ndim()) +
                      " dimensions");
  require_mpi("DistributedIndex.remove");
  bhcl::DistributedUpdateStats us;
  {
    py::gil_scoped_release nogil;
    index.remove(ids.data(), static_cast<std::size_t>(ids.shape(0)), &us);
  }
  return update_stats_dict(us);
}

py::dict build_stats(const bhcl::DistributedIndex& index) {
  const bhcl::DistributedBuildStats& b = index.build_stats();
  py::dict o;
  o["n_global"] = b.n_global;
  o["n_input"] = b.n_input;
  o["shard_points"] = b.shard_points;
  o["points_sent"] = b.points_sent;
  o["points_received"] = b.points_received;
  o["shard_points_all"] = b.shard_points_all;
  o["balance"] = b.balance;
  o["shard_s"] = b.shard_s;
  o["build_s"] = b.build_s;
  o["wall_s"] = b.wall_s;
  return o;
}

}  // namespace

void bind_distributed(py::module_& m) {
  m.def("mpi_world", &world, "MPI_COMM_WORLD's Fortran handle, MPI initialised first where nobody has.");
  m.def("mpi_finalize", &finalize, "MPI_Finalize, where mpi_world initialised MPI.");
  m.def("mpi_usable", &mpi_usable, "Whether MPI is initialised and not finalised.");

  py::class_<Comm, std::shared_ptr<Comm>>(m, "MpiComm")
      .def(py::init<int, double>(), py::arg("handle"), py::arg("deadline_s"))
      .def_property_readonly("rank", &Comm::rank)
      .def_property_readonly("size", &Comm::size)
      .def("agree", &Comm::agree, py::arg("local_error"), py::arg("what"))
      .def("box", &Comm::box, py::arg("lo"), py::arg("hi"));

  using D = bhcl::DistributedIndex;
  py::class_<D, bhcl::SearchIndex, std::unique_ptr<D>>(m, "DistributedIndex")
      .def(py::init(&build), py::arg("comm"), py::arg("runtime"), py::arg("points").noconvert(),
           py::arg("method"), py::arg("options"), py::arg("boxes_per_rank"), py::arg("border_factor"),
           py::arg("deadline_s"), py::arg("id_base"))
      .def_property_readonly("rank", &D::rank)
      .def_property_readonly("ranks", &D::ranks)
      .def_property_readonly("id_base", &D::id_base)
      .def_property_readonly("id_bound", &D::id_bound)
      .def_property_readonly("shard_size", &D::shard_size)
      .def_property_readonly("shard_ids", [](const D& x) {
        std::vector<std::int64_t> ids = x.shard_ids();
        const auto n = static_cast<py::ssize_t>(ids.size());
        return to_numpy(std::move(ids), {n});
      })
      .def_property_readonly("shard_live_ids", [](const D& x) {
        std::vector<std::int64_t> ids = x.shard_live_ids();
        const auto n = static_cast<py::ssize_t>(ids.size());
        return to_numpy(std::move(ids), {n});
      })
      .def_property_readonly("removed_count", &D::removed_count)
      // This rank's: the local index's structure and host copies (as Index's memory_bytes +
      // host_bytes), and the distributed index's own host arrays (host_bytes: the shard's global
      // ids, its copy of the points, their sub-runs and removed marks).
      .def_property_readonly("memory_bytes", [](const D& x) {
        const bhcl::Index* l = x.local_index();
        return (l ? l->memory_bytes() + l->host_bytes() : std::size_t(0)) + x.host_bytes();
      })
      .def_property_readonly("host_bytes", &D::host_bytes)
      .def_property_readonly("build_stats", &build_stats)
      .def_property_readonly("runtime", [](const D& x) -> std::shared_ptr<bhcl::Runtime> {
        const bhcl::Index* l = x.local_index();
        return l ? l->runtime_ptr() : nullptr;
      })
      .def("query", &knn, py::arg("queries").noconvert(), py::arg("params"))
      .def("radius_search", &radius, py::arg("queries").noconvert(), py::arg("r"), py::arg("params"))
      .def("insert", &insert_points, py::arg("points").noconvert())
      .def("remove", &remove_ids, py::arg("ids").noconvert());
}
