// The query path's Hilbert order (core/query_order.cpp): its branch-free keys equal the curve's
// reference encoder, and the parallel radix sort gives the stable sort by (key, index).
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <mutex>
#include <random>
#include <vector>

#include "core/query_order.hpp"
#include "sfc/hilbert.hpp"
#include "test_util.hpp"

TEST_CASE("query order: branch-free 16-bit Hilbert keys equal sfc::hilbert_encode") {
  std::mt19937 rng(7);
  std::uniform_int_distribution<std::uint32_t> cell(0, 0xffff);
  const std::uint32_t edges[] = {0, 1, 2, 0x7fff, 0x8000, 0xfffe, 0xffff};
  for (std::uint32_t x : edges)
    for (std::uint32_t y : edges)
      for (std::uint32_t z : edges) REQUIRE(bhcl::detail::hilbert_key16(x, y, z) == bhcl::sfc::hilbert_encode(x, y, z, 16));
  for (int i = 0; i < 200000; ++i) {
    const std::uint32_t x = cell(rng), y = cell(rng), z = cell(rng);
    REQUIRE(bhcl::detail::hilbert_key16(x, y, z) == bhcl::sfc::hilbert_encode(x, y, z, 16));
  }
}

namespace {
// The reference: the finite queries' keys over their own box, sorted stably, then the rest.
std::vector<std::size_t> reference_order(const std::vector<float>& q, std::size_t n) {
  std::vector<std::size_t> finite, rest;
  for (std::size_t i = 0; i < n; ++i)
    (std::isfinite(q[3 * i]) && std::isfinite(q[3 * i + 1]) && std::isfinite(q[3 * i + 2]) ? finite : rest).push_back(i);
  std::vector<float> compact;
  for (std::size_t i : finite) compact.insert(compact.end(), &q[3 * i], &q[3 * i] + 3);
  const auto qz = bhcl::sfc::make_quantiser(compact.data(), finite.size(), 16);
  const auto keys = bhcl::sfc::hilbert_keys(compact.data(), finite.size(), qz);
  std::vector<std::size_t> want;
  for (std::int32_t j : bhcl::sfc::hilbert_order(keys)) want.push_back(finite[static_cast<std::size_t>(j)]);
  want.insert(want.end(), rest.begin(), rest.end());
  return want;
}
}  // namespace

TEST_CASE("query order: clustered queries (large buckets, sorted by radix) keep the stable order by (key, index)") {
  // Most queries on a thin sphere in one corner of a box stretched by a few far ones: the key's
  // top-bit buckets then hold hundreds to thousands of distinct keys each, which the bucket pass
  // sorts by 6-bit radix levels down to runs of kSubMin and insertion sort below; some exact duplicates too.
  // The pipeline's form (fresh memory, not filled first) gives the same order.
  for (const std::size_t n : {std::size_t(100003), std::size_t(300000)}) {
    CAPTURE(n);
    std::mt19937 rng(11);
    std::normal_distribution<float> g(0.0f, 1.0f);
    std::vector<float> q(3 * n);
    for (std::size_t i = 0; i < n; ++i) {
      float v[3] = {g(rng), g(rng), g(rng)};
      const float r = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) + 1e-6f;
      for (int d = 0; d < 3; ++d) q[3 * i + d] = 0.01f * v[d] / r;
    }
    for (std::size_t i = 0; i < n; i += 5003) q[3 * i] = 100.0f;  // the box 10^4 times the sphere
    for (std::size_t i = 1; i < n; i += 13) std::copy_n(&q[3 * (i - 1)], 3, &q[3 * i]);  // duplicates
    q[3 * 17 + 2] = NAN;
    const std::vector<std::size_t> want = reference_order(q, n);
    CHECK(bhcl::detail::hilbert_query_order(q.data(), n) == want);
    const auto fresh = bhcl::detail::hilbert_query_order_fresh(q.data(), n);
    CHECK(std::equal(want.begin(), want.end(), fresh.get()));
  }
}

TEST_CASE("query order: the parallel order equals the stable sort by (key, index), non-finite last") {
  // 50k queries (over the threaded path's threshold) with duplicates (equal keys), NaNs and
  // infinities; also a count whose threads' ranges end inside a block of keys (the key loop
  // computes every lane of a block of kLanes: the tail's spare lanes must not land in the order).
  for (const std::size_t n : {std::size_t(50000), std::size_t(50007)}) {
    CAPTURE(n);
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> u(-5.0f, 5.0f);
    std::vector<float> q(3 * n);
    for (auto& v : q) v = u(rng);
    for (std::size_t i = 0; i < n; i += 7) std::copy_n(&q[0], 3, &q[3 * i]);  // many equal keys
    for (std::size_t i = 5; i < n; i += 1001) q[3 * i + 1] = NAN;
    for (std::size_t i = 9; i < n; i += 2003) q[3 * i + 2] = (i / 2003) % 2 ? INFINITY : -INFINITY;
    const std::vector<std::size_t> got = bhcl::detail::hilbert_query_order(q.data(), n);
    CHECK(got == reference_order(q, n));
  }
}

TEST_CASE("query order: the sink sees every position once, each range after its order is final") {
  // The query pipeline gathers the queries in the sort's last pass (OrderSink): every position
  // in exactly one range, and order[lo, hi) there equal to the final order. One thread (small
  // n), the threaded bucket path, and all queries non-finite (the identity order).
  for (const std::size_t n : {std::size_t(2), std::size_t(1000), std::size_t(50007), std::size_t(3)}) {
    CAPTURE(n);
    std::mt19937 rng(11);
    std::uniform_real_distribution<float> u(-5.0f, 5.0f);
    std::vector<float> q(3 * n);
    for (auto& v : q) v = n == 3 ? NAN : u(rng);
    std::vector<std::size_t> seen(n, ~std::size_t(0));
    std::vector<int> times(n, 0);
    std::mutex m;
    bool bad = false;  // (no assertion on the sort's threads)
    const bhcl::detail::OrderSink sink = [&](std::size_t lo, std::size_t hi, const std::size_t* order) {
      std::lock_guard<std::mutex> lock(m);
      if (!(lo < hi && hi <= n)) {
        bad = true;
        return;
      }
      for (std::size_t i = lo; i < hi; ++i) {
        seen[i] = order[i];
        ++times[i];
      }
    };
    const auto got = bhcl::detail::hilbert_query_order_fresh(q.data(), n, nullptr, &sink);
    CHECK_FALSE(bad);
    CHECK(std::count(times.begin(), times.end(), 1) == static_cast<std::ptrdiff_t>(n));
    CHECK(std::equal(seen.begin(), seen.end(), got.get()));
    CHECK(seen == reference_order(q, n));
  }
}
