// MultiDeviceIndex: one index per device, batches split by measured throughput, parts run on
// their own host threads, rows merged in the caller's order.
#include "blockhash_cl/multi_device.hpp"

#include <algorithm>
#include <cmath>
#include <exception>
#include <numeric>
#include <thread>

#include "blockhash_cl/error.hpp"
#include "core/parallel.hpp"

namespace bhcl {

namespace {

// Runs fn(d) for every device on its own thread; rethrows the first failure, naming the device.
template <typename Fn>
void on_each_device(std::size_t devices, const std::vector<std::string>& names, Fn&& fn) {
  detail::parallel_tasks(devices, [&](std::size_t d) {
    try {
      fn(d);
    } catch (const std::exception& e) {
      throw Error("device " + std::to_string(d) + " (" + names[d] + "): " + e.what());
    }
  });
}

// A part's time: its wall time without compiles, not its kernel event time. Devices that share
// hardware (two PoCL contexts on one CPU) each report kernel time while the other waits, which
// would show a speed-up that is not there.
double part_seconds(const QueryStats& s) { return std::max(0.0, s.wall_s - s.compile_s); }

// Adds one device's part to a call's stats: counts and transfer times sum; query_s and wall_s are
// the slowest part's (the batch's critical path).
void add_part(QueryStats& total, const QueryStats& part) {
  const double query_s = std::max(total.query_s, part_seconds(part));
  total.add_slice(part);
  total.query_s = query_s;
  total.wall_s = std::max(total.wall_s, part.wall_s);
}

}  // namespace

std::vector<std::string> split_device_list(const std::string& list) {
  std::vector<std::string> out;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = list.find(',', start);
    std::string item = list.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    if (item.empty()) throw Error("device list '" + list + "': an empty entry (specs are comma separated)");
    out.push_back(item);
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return out;
}

MultiDeviceIndex::MultiDeviceIndex(std::vector<std::shared_ptr<Runtime>> runtimes,
                                   const std::string& method, const float* points,
                                   std::size_t n_points, const MethodOptions& options) {
  if (runtimes.empty()) throw Error("MultiDeviceIndex: no devices (an empty runtime list)");
  std::vector<std::string> names;
  for (std::size_t d = 0; d < runtimes.size(); ++d) {
    if (!runtimes[d]) throw Error("MultiDeviceIndex: runtime " + std::to_string(d) + " is null");
    names.push_back(runtimes[d]->info().summary());
  }
  if (!options.save_index().empty())
    throw Error("MultiDeviceIndex: save_index does not apply (save a single-device index)");
  indexes_.resize(runtimes.size());
  on_each_device(runtimes.size(), names, [&](std::size_t d) {
    indexes_[d] = make_index(method, runtimes[d], points, n_points, options);
  });
  weights_.assign(runtimes.size(), 1.0 / double(runtimes.size()));
}

// Updates: the first copy checks the input (its errors leave every copy unchanged), then the
// others follow one by one (the copies' builds differ per device, so each updates its own).
std::int32_t MultiDeviceIndex::insert(const float* points, std::size_t n) {
  std::lock_guard<std::mutex> gate(update_gate_);  // writer preference
  std::unique_lock<std::shared_mutex> lock(update_mutex_);
  const std::int32_t first = indexes_.front()->insert(points, n);
  for (std::size_t d = 1; d < indexes_.size(); ++d) {
    try {
      if (indexes_[d]->insert(points, n) != first) throw Error("the copies' ids differ");
    } catch (const std::exception& e) {
      throw Error("multi-device insert: device " + std::to_string(d) + " (" + indexes_[d]->runtime().info().summary() +
                  "): " + e.what() + "; the copies now differ, rebuild the index");
    }
  }
  return first;
}

void MultiDeviceIndex::remove(const std::int32_t* ids, std::size_t n) {
  std::lock_guard<std::mutex> gate(update_gate_);  // writer preference
  std::unique_lock<std::shared_mutex> lock(update_mutex_);
  indexes_.front()->remove(ids, n);
  for (std::size_t d = 1; d < indexes_.size(); ++d) {
    try {
      indexes_[d]->remove(ids, n);
    } catch (const std::exception& e) {
      throw Error("multi-device remove: device " + std::to_string(d) + " (" + indexes_[d]->runtime().info().summary() +
                  "): " + e.what() + "; the copies now differ, rebuild the index");
    }
  }
}

std::vector<double> MultiDeviceIndex::weights() const {
  std::lock_guard<std::mutex> lock(weights_mutex_);
  return weights_;
}

void MultiDeviceIndex::set_weights(const std::vector<double>& w) {
  if (w.size() != indexes_.size())
    throw Error("set_weights: " + std::to_string(w.size()) + " weights for " + std::to_string(indexes_.size()) + " devices");
  double sum = 0;
  for (double x : w) {
    if (!(x >= 0) || !std::isfinite(x)) throw Error("set_weights: weights must be finite and >= 0");
    sum += x;
  }
  if (!(sum > 0)) throw Error("set_weights: the weights sum to 0");
  std::lock_guard<std::mutex> lock(weights_mutex_);
  for (std::size_t d = 0; d < w.size(); ++d) weights_[d] = w[d] / sum;
}

std::vector<std::size_t> MultiDeviceIndex::split(std::size_t n) const {
  const std::vector<double> w = weights();
  std::vector<std::size_t> first(w.size() + 1, 0);
  double acc = 0;
  for (std::size_t d = 0; d < w.size(); ++d) {
    acc += w[d];
    first[d + 1] = d + 1 == w.size() ? n : std::min(n, static_cast<std::size_t>(std::llround(acc * double(n))));
    first[d + 1] = std::max(first[d + 1], first[d]);
  }
  return first;
}

std::vector<double> adapted_weights(const std::vector<double>& old, const std::vector<std::size_t>& counts,
                                    const std::vector<double>& seconds) {
  if (counts.size() != old.size() || seconds.size() != old.size())
    throw Error("adapted_weights: " + std::to_string(old.size()) + " weights, " + std::to_string(counts.size()) +
                " counts and " + std::to_string(seconds.size()) + " times");
  std::vector<double> qps(counts.size(), 0);
  double sum = 0;
  for (std::size_t d = 0; d < counts.size(); ++d)
    if (counts[d] >= 256 && seconds[d] > 0 && std::isfinite(seconds[d])) sum += qps[d] = double(counts[d]) / seconds[d];
  double known = 0;
  for (std::size_t d = 0; d < counts.size(); ++d) known += qps[d] > 0 ? old[d] : 0;
  std::vector<double> w = old;
  if (sum <= 0 || known <= 0) return w;
  for (std::size_t d = 0; d < counts.size(); ++d)
    if (qps[d] > 0) w[d] = 0.5 * old[d] + 0.5 * known * qps[d] / sum;
  return w;
}

void MultiDeviceIndex::learn(const std::vector<std::size_t>& counts, const std::vector<double>& seconds) const {
  std::lock_guard<std::mutex> lock(weights_mutex_);
  weights_ = adapted_weights(weights_, counts, seconds);
}

QueryStats MultiDeviceIndex::on_devices(
    std::size_t n, const std::function<QueryStats(std::size_t, std::size_t, std::size_t)>& run,
    const std::function<void(std::size_t, std::size_t)>& merge, std::vector<DeviceShare>* shares) const {
  std::unique_lock<std::mutex> gate(update_gate_);
  std::shared_lock<std::shared_mutex> lock(update_mutex_);
  gate.unlock();
  const std::size_t D = indexes_.size();
  const std::vector<double> w = weights();
  const std::vector<std::size_t> first = split(n);
  std::vector<QueryStats> st(D);
  std::vector<std::string> names;
  for (const auto& ix : indexes_) names.push_back(ix->runtime().info().summary());
  on_each_device(D, names, [&](std::size_t d) { st[d] = run(d, first[d], first[d + 1] - first[d]); });
  QueryStats total;
  total.n_queries = n;
  std::vector<std::size_t> counts(D);
  std::vector<double> seconds(D);
  for (std::size_t d = 0; d < D; ++d) {
    merge(d, first[d]);
    add_part(total, st[d]);
    counts[d] = first[d + 1] - first[d];
    seconds[d] = part_seconds(st[d]);
    if (shares) shares->push_back({names[d], counts[d], w[d], st[d]});
  }
  learn(counts, seconds);
  return total;
}

QueryStats MultiDeviceIndex::query(const float* queries, std::size_t n, const SearchParams& params,
                                   KnnResult& out, std::vector<DeviceShare>* shares) const {
  std::vector<KnnResult> parts(indexes_.size());
  const std::size_t k = static_cast<std::size_t>(params.k);
  return on_devices(
      n,
      [&](std::size_t d, std::size_t first, std::size_t m) {
        return indexes_[d]->query(queries + 3 * first, m, params, parts[d]);
      },
      [&](std::size_t d, std::size_t first) {
        if (d == 0) {
          out.resize(n, params.k);
          if (params.count_examined) out.examined.assign(n, 0);
        }
        std::copy(parts[d].ids.begin(), parts[d].ids.end(), out.ids.begin() + first * k);
        std::copy(parts[d].dist2.begin(), parts[d].dist2.end(), out.dist2.begin() + first * k);
        std::copy(parts[d].counts.begin(), parts[d].counts.end(), out.counts.begin() + first);
        if (params.count_examined)
          std::copy(parts[d].examined.begin(), parts[d].examined.end(), out.examined.begin() + first);
      },
      shares);
}

QueryStats MultiDeviceIndex::radius_search(const float* queries, std::size_t n, float r,
                                           const RadiusParams& params, RadiusResult& out,
                                           std::vector<DeviceShare>* shares) const {
  std::vector<RadiusResult> parts(indexes_.size());
  return on_devices(
      n,
      [&](std::size_t d, std::size_t first, std::size_t m) {
        return indexes_[d]->radius_search(queries + 3 * first, m, r, params, parts[d]);
      },
      [&](std::size_t d, std::size_t) {
        if (d == 0) {
          out = RadiusResult{};
          out.n = n;
          out.offsets.assign(1, 0);
        }
        out.append(parts[d]);
      },
      shares);
}

}  // namespace bhcl
