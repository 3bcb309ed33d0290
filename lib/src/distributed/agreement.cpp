#include "distributed/agreement.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <thread>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/numbers.hpp"

namespace bhcl::distributed {

namespace {

std::string f32(float v) {
  return detail::format_general(double(v), 9);  // locale-free (numbers.hpp)
}
std::string f64(double v) {
  return detail::format_general(v, 17);
}
std::string z(std::size_t v) { return std::to_string(v); }

std::uint64_t fnv1a(const Parameters& ps) {
  std::uint64_t h = 1469598103934665603ull;
  auto add = [&](const std::string& s) {
    for (unsigned char c : s) h = (h ^ c) * 1099511628211ull;
    h = (h ^ 0xffu) * 1099511628211ull;  // a separator no text holds
  };
  for (const auto& [n, v] : ps) add(n), add(v);
  return h;
}

std::string serialise(const Parameters& ps) {
  std::string s;
  for (const auto& [n, v] : ps) s += n + '\0' + v + '\0';
  return s;
}

Parameters parse(const char* p, std::size_t len) {
  Parameters out;
  std::size_t i = 0;
  while (i < len) {
    const std::string n(p + i);
    i += n.size() + 1;
    const std::string v = i < len ? std::string(p + i) : std::string();
    i += v.size() + 1;
    out.emplace_back(n, v);
  }
  return out;
}

// The first parameter whose value differs (an absent one reads "(not set)"), or empty.
std::string first_difference(const Parameters& ref, const Parameters& other, int rank) {
  std::map<std::string, std::string> a(ref.begin(), ref.end()), b(other.begin(), other.end());
  std::vector<std::string> names;
  for (const auto& [n, v] : ref) names.push_back(n);
  for (const auto& [n, v] : other)
    if (!a.count(n)) names.push_back(n);
  for (const auto& n : names) {
    const std::string va = a.count(n) ? a[n] : "(not set)", vb = b.count(n) ? b[n] : "(not set)";
    if (va != vb)
      return "rank " + std::to_string(rank) + " has " + n + " = " + vb + " where rank 0 has " + va;
  }
  return {};
}

int deadline_keyval() {
  static int key = [] {
    int k = MPI_KEYVAL_INVALID;
    // The slot is freed with its communicator.
    MPI_Comm_delete_attr_function* del = [](MPI_Comm, int, void* v, void*) {
      delete static_cast<double*>(v);
      return MPI_SUCCESS;
    };
    MPI_Comm_create_keyval(MPI_COMM_NULL_COPY_FN, del, &k, nullptr);
    return k;
  }();
  return key;
}

// Per communicator: the deadline set on it (an attribute holding a double).
double* deadline_slot(MPI_Comm comm, bool create) {
  void* v = nullptr;
  int found = 0;
  MPI_Comm_get_attr(comm, deadline_keyval(), &v, &found);
  if (found) return static_cast<double*>(v);
  if (!create) return nullptr;
  double* slot = new double(-1);
  MPI_Comm_set_attr(comm, deadline_keyval(), slot);
  return slot;
}

bool parse_env_deadline(double& out) {
  const char* e = std::getenv("BHCL_MPI_DEADLINE_S");
  if (!e || !*e) return false;
  double v = 0;
  if (detail::parse_double(e, v) != detail::NumberParse::Ok || !(v >= 0) || std::isinf(v)) return false;
  out = v;
  return true;
}

constexpr int kTagIn = 22022, kTagOut = 22023;

[[noreturn]] void end_job(MPI_Comm comm, const std::string& text) {
  std::fprintf(stderr, "%s\n", text.c_str());
  std::fflush(stderr);
  MPI_Abort(comm, 124);
  std::abort();  // MPI_Abort does not return
}

// Polls `reqs` until all complete (true) or `seconds` pass (false), sleeping between polls so
// that a waiting rank leaves the cores to the ranks still working.
bool poll_all(std::vector<MPI_Request>& reqs, double seconds) {
  const auto t0 = std::chrono::steady_clock::now();
  int us = 0;
  for (;;) {
    int done = 0;
    MPI_Testall(static_cast<int>(reqs.size()), reqs.data(), &done, MPI_STATUSES_IGNORE);
    if (done) return true;
    if (seconds > 0 && std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() > seconds)
      return false;
    us = std::min(us + 10, 1000);
    std::this_thread::sleep_for(std::chrono::microseconds(us));
  }
}

std::string seconds_text(double s) {
  return detail::format_general(s, 6);
}

}  // namespace

Parameters build_parameters(const DistributedBuildParams& p) {
  Parameters ps = {{"method", p.method},
                   {"boxes_per_rank", std::to_string(p.boxes_per_rank)},
                   {"border_factor", f32(p.border_factor)},
                   {"deadline_s", f64(p.deadline_s)},
                   {"id_base", std::to_string(p.id_base)}};
  for (const auto& [n, v] : p.options.values) ps.emplace_back("option " + n, v);
  return ps;
}

Parameters search_parameters(const SearchParams& p) {
  return {{"k", std::to_string(p.k)},
          {"max_radius", f32(p.max_radius)},
          {"A", f32(p.A)},
          {"recall_target", f64(p.recall_target)},
          {"neighbour_probes", std::to_string(p.neighbour_probes)},
          {"local_size", z(p.local_size)},
          {"max_batch", z(p.max_batch)},
          {"sort_queries", std::to_string(p.sort_queries)},
          {"kernel_defines", p.kernel_defines},
          {"count_examined", p.count_examined ? "true" : "false"}};
}

Parameters radius_parameters(float r, const RadiusParams& p) {
  return {{"radius", f32(r)},
          {"budget", std::to_string(p.budget)},
          {"neighbour_probes", std::to_string(p.neighbour_probes)},
          {"max_results", z(p.max_results)},
          {"sorted", p.sorted ? "true" : "false"},
          {"local_size", z(p.local_size)},
          {"max_batch", z(p.max_batch)},
          {"sort_queries", std::to_string(p.sort_queries)},
          {"kernel_defines", p.kernel_defines},
          {"count_examined", p.count_examined ? "true" : "false"},
          {"max_batch_results", z(p.max_batch_results)}};
}

void agree_parameters(MPI_Comm comm, const Parameters& mine, const std::string& what) {
  int rank = 0, ranks = 1;
  MPI_Comm_rank(comm, &rank);
  MPI_Comm_size(comm, &ranks);
  const std::uint64_t h = fnv1a(mine);
  std::uint64_t v[2] = {h, ~h}, g[2];
  MPI_Allreduce(v, g, 2, MPI_UINT64_T, MPI_MIN, comm);
  if (g[0] == ~g[1]) return;  // min == max: one hash on every rank
  // Differ somewhere: every rank gathers every rank's text and writes the same message.
  const std::string text = serialise(mine);
  int len = static_cast<int>(text.size());
  std::vector<int> lens(static_cast<std::size_t>(ranks)), displ(static_cast<std::size_t>(ranks));
  MPI_Allgather(&len, 1, MPI_INT, lens.data(), 1, MPI_INT, comm);
  int total = 0;
  for (int r = 0; r < ranks; ++r) displ[static_cast<std::size_t>(r)] = total, total += lens[static_cast<std::size_t>(r)];
  std::vector<char> all(static_cast<std::size_t>(std::max(total, 1)));
  MPI_Allgatherv(text.data(), len, MPI_CHAR, all.data(), lens.data(), displ.data(), MPI_CHAR, comm);
  const Parameters ref = parse(all.data(), static_cast<std::size_t>(lens[0]));
  std::string first;
  int differ = 0;
  for (int r = 1; r < ranks; ++r) {
    const std::size_t rr = static_cast<std::size_t>(r);
    const std::string d = first_difference(ref, parse(all.data() + displ[rr], static_cast<std::size_t>(lens[rr])), r);
    if (d.empty()) continue;
    ++differ;
    if (first.empty()) first = d;
  }
  std::string msg = what + ": the ranks passed different parameters: " + first;
  if (differ > 1) msg += " (and " + std::to_string(differ - 1) + " other rank" + (differ > 2 ? "s" : "") + " differ)";
  msg += "; every rank must pass the same ones";
  throw Error(msg);
}

double deadline_seconds(MPI_Comm comm) {
  if (const double* s = deadline_slot(comm, false); s && *s >= 0) return *s;
  double e = 0;
  if (parse_env_deadline(e)) return e;
  return kDefaultDeadlineS;
}

void set_deadline(MPI_Comm comm, double seconds) { *deadline_slot(comm, true) = seconds; }

std::string deadline_env_error() {
  const char* e = std::getenv("BHCL_MPI_DEADLINE_S");
  double v = 0;
  if (!e || !*e || parse_env_deadline(v)) return {};
  return std::string("BHCL_MPI_DEADLINE_S must be a number of seconds >= 0 (0: no deadline), got '") + e + "'";
}

void gate(MPI_Comm comm, const std::string& step) {
  int rank = 0, ranks = 1;
  MPI_Comm_rank(comm, &rank);
  MPI_Comm_size(comm, &ranks);
  if (ranks == 1) return;
  const double T = deadline_seconds(comm);
  const std::string tail = " (deadline " + seconds_text(T) +
                           " s: DistributedBuildParams::deadline_s or BHCL_MPI_DEADLINE_S): ending the job";
  if (rank == 0) {
    std::vector<int> tokens(static_cast<std::size_t>(ranks - 1));
    std::vector<MPI_Request> reqs(tokens.size());
    for (int r = 1; r < ranks; ++r)
      MPI_Irecv(&tokens[static_cast<std::size_t>(r - 1)], 1, MPI_INT, r, kTagIn, comm, &reqs[static_cast<std::size_t>(r - 1)]);
    if (!poll_all(reqs, T)) {
      std::string missing;
      int count = 0;
      for (int r = 1; r < ranks; ++r) {
        int done = 0;
        MPI_Test(&reqs[static_cast<std::size_t>(r - 1)], &done, MPI_STATUS_IGNORE);
        if (!done) missing += (count++ ? ", " : "") + std::to_string(r);
      }
      end_job(comm, step + ": rank" + (count > 1 ? "s " : " ") + missing + " did not answer within " +
                        seconds_text(T) + " s" + tail);
    }
    const int go = -1;
    std::vector<MPI_Request> sends(tokens.size());
    for (int r = 1; r < ranks; ++r)
      MPI_Isend(&go, 1, MPI_INT, r, kTagOut, comm, &sends[static_cast<std::size_t>(r - 1)]);
    if (!poll_all(sends, T))
      end_job(comm, step + ": rank 0 could not reach the other ranks within " + seconds_text(T) + " s" + tail);
    return;
  }
  // Another rank: check in, then wait for rank 0's word. Rank 0 itself waits up to T for the
  // slowest rank and then names it, so this rank waits longer before it names rank 0.
  int token = rank, verdict = 0;
  std::vector<MPI_Request> reqs(2);
  MPI_Isend(&token, 1, MPI_INT, 0, kTagIn, comm, &reqs[0]);
  MPI_Irecv(&verdict, 1, MPI_INT, 0, kTagOut, comm, &reqs[1]);
  if (!poll_all(reqs, T > 0 ? 2 * T + 5 : 0))
    end_job(comm, step + ": rank 0 did not answer rank " + std::to_string(rank) + " within " +
                      seconds_text(2 * T + 5) + " s" + tail);
}

}  // namespace bhcl::distributed
