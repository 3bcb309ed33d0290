#include "result_files.hpp"

#include <cctype>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include <sys/mman.h>
#include <unistd.h>

#include "blockhash_cl/error.hpp"
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/parallel.hpp"
#include "cli.hpp"

namespace bhcl::cli {

namespace {
// The ids of a part in the file's width: as they are when it matches, else converted (int64 ids
// written as int32 fit: the caller chose the width from the largest id).
template <typename Out, typename In>
const Out* ids_as(const std::vector<In>& ids, std::size_t count, std::vector<Out>& tmp) {
  if constexpr (std::is_same_v<Out, In>) {
    return ids.data();
  } else {
    tmp.assign(ids.begin(), ids.begin() + static_cast<std::ptrdiff_t>(count));
    return tmp.data();
  }
}

// Mapped outputs of at least this size are advised MADV_HUGEPAGE before their pages are made
// present: the page cache then hands out 2 MiB folios, one fault and one ext4 page_mkwrite each
// instead of 512 (a 4 KiB page costs 5-7 us on the VMs measured). bhcl knn, Cornell 1M, 1M
// queries, AVX-512, 2 threads, alternating processes: the write stage at k = 10 (80 MB) 15.7
// against 28.6 ms, at k = 50 (400 MB) 83 against 229 ms (medians of 6), the kernel's time the
// same. The page cache's large folios come from readahead, whose allocations give up (small
// folios then) rather than compact hard as huge anonymous pages did in python/bindings.cpp's
// refinement; not measured under memory pressure.
constexpr std::size_t kHugeAdviceBytes = std::size_t(2) << 20;

bool is_npy(const std::string& path) {
  if (path.size() < 4) return false;
  std::string e = path.substr(path.size() - 4);
  for (char& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e == ".npy";
}
}  // namespace

ArrayOutput::ArrayOutput(const std::string& path, const char* descr, std::size_t item, std::int64_t rows,
                         std::size_t cols)
    : file_(path, is_npy(path) ? "the NPY array" : "the raw array"), descr_(descr), item_(item), cols_(cols),
      rows_(rows), npy_(is_npy(path)) {
  std::string h;
  if (npy_) {
    // An unknown length: the header of the longest one (20 digits) now, rewritten at the end.
    h = header(rows_ >= 0 ? static_cast<std::uint64_t>(rows_) : ~std::uint64_t(0));
    header_bytes_ = h.size();
  }
  // A known length: the header stored through the mapping with the rows (map_known_length), not
  // written first: a write() leaves the file's first page a 4 KiB folio in the page cache, and
  // then the whole first 2 MiB of the mapping is made of 4 KiB pages (no huge folio can hold it).
  if (!map_known_length(h)) file_.write(h.data(), h.size());
}

bool ArrayOutput::map_known_length(const std::string& head) {
  if (rows_ < 0) return false;
  const std::size_t bytes = static_cast<std::size_t>(rows_) * (cols_ ? cols_ : 1) * item_;
  if (bytes == 0) return false;
  char* const m = static_cast<char*>(file_.map_append(head.size() + bytes));
  if (!m) return false;
#ifdef MADV_HUGEPAGE
  if (head.size() + bytes >= kHugeAdviceBytes) {
    // The mapping starts on a page (it maps the file from offset 0): m is its first byte.
    (void)::madvise(m, head.size() + bytes, MADV_HUGEPAGE);
  }
#endif
  // The header's page made present after the advice: the first 2 MiB a huge folio like the rest.
  std::memcpy(m, head.data(), head.size());
  mapped_ = m + head.size();
  return true;
}

std::string ArrayOutput::header(std::uint64_t rows) const {
  // Padded to the length of the header written first, when this one replaces it.
  return npy_header(descr_.c_str(), rows, cols_, header_bytes_);
}

void ArrayOutput::populate_next(std::size_t items) const {
  char* at = static_cast<char*>(next());
  if (!at || items == 0) return;
  const std::uintptr_t page = static_cast<std::uintptr_t>(::sysconf(_SC_PAGESIZE));
  const std::uintptr_t lo = reinterpret_cast<std::uintptr_t>(at) / page * page;
  const std::uintptr_t hi = reinterpret_cast<std::uintptr_t>(at) + items * item_;
  // Advice only: where the kernel has no MADV_POPULATE_WRITE (before 5.14) the search faults them.
  (void)::madvise(reinterpret_cast<void*>(lo), hi - lo, MADV_POPULATE_WRITE);
}

void ArrayOutput::append(const void* data, std::size_t items) {
  if (!mapped_) {
    file_.write(data, items * item_);
  } else {
    const std::uint64_t total = static_cast<std::uint64_t>(rows_) * (cols_ ? cols_ : 1);
    if (items_ + items > total)
      throw Error(file_.path() + ": internal error: " + std::to_string(items_ + items) + " items written of " +
                  std::to_string(total));
    char* at = mapped_ + items_ * item_;
    if (data != at) std::memcpy(at, data, items * item_);  // else stored there by the search
  }
  items_ += items;
}

void ArrayOutput::commit() {
  const std::uint64_t per = cols_ ? cols_ : 1;
  const std::uint64_t rows = items_ / per;
  if (rows_ >= 0 && rows != static_cast<std::uint64_t>(rows_))
    throw Error(file_.path() + ": internal error: " + std::to_string(rows) + " rows written of " + std::to_string(rows_));
  if (npy_ && rows_ < 0) {
    const std::string h = header(rows);
    file_.write_at(0, h.data(), h.size());
  }
  file_.commit();
}

KnnOutputs::KnnOutputs(const Args& args, std::size_t n, int k, bool ids64) : ids64_(ids64) {
  const std::int64_t rows = static_cast<std::int64_t>(n);
  const std::size_t cols = static_cast<std::size_t>(k);
  ids_ = std::make_unique<ArrayOutput>(args.str("out-ids"), ids64 ? "<i8" : "<i4", ids64 ? 8 : 4, rows, cols);
  dist2_ = std::make_unique<ArrayOutput>(args.str("out-dist2"), "<f4", 4, rows, cols);
  if (args.has("out-counts")) counts_ = std::make_unique<ArrayOutput>(args.str("out-counts"), "<i4", 4, rows, 0);
}

void KnnSlice::reserve(std::size_t rows, int k_, bool examined) {
  const std::size_t kk = static_cast<std::size_t>(k_);
  if (rows <= capacity_ && k_ == k && (examined_ || !examined)) return;
  check_result_memory(rows, k_, examined, 1, "bhcl knn");
  // new T[] default-initialises: the pages stay untouched until the search writes them.
  ids_.reset(new std::int32_t[std::max<std::size_t>(1, rows * kk)]);
  dist2_.reset(new float[std::max<std::size_t>(1, rows * kk)]);
  counts_.reset(new std::int32_t[std::max<std::size_t>(1, rows)]);
  examined_.reset(examined ? new std::int32_t[std::max<std::size_t>(1, rows)] : nullptr);
  capacity_ = rows;
  k = k_;
}

void KnnOutputs::append(const KnnResult& part) { append_part(part); }

KnnRowsView KnnOutputs::rows_for(const KnnSlice& part) const { return rows_at_next(part, true); }

KnnRowsView KnnOutputs::rows_at_next(const KnnSlice& part, bool populate) const {
  KnnRowsView v = part.view();
  if (ids64_) return v;  // the search's int32 ids are widened on the way to the file
  if (populate) {
    // One file a thread (as the writes were): the two mappings' faults do not contend.
    const std::size_t items = part.n * static_cast<std::size_t>(part.k);
    detail::parallel_tasks(2, [&](std::size_t t) { (t ? dist2_ : ids_)->populate_next(items); });
  }
  if (void* at = ids_->next()) v.ids = static_cast<std::int32_t*>(at);
  if (void* at = dist2_->next()) v.dist2 = static_cast<float*>(at);
  return v;
}

void KnnOutputs::append(const KnnSlice& part) {
  const std::size_t nk = part.n * static_cast<std::size_t>(part.k);
  const KnnRowsView v = rows_at_next(part, false);
  if (ids64_) {
    std::vector<std::int64_t> wide(v.ids, v.ids + nk);
    ids_->append(wide.data(), nk);
  } else {
    append_ids_and_dist2(v.ids, v.dist2, nk);
  }
  if (ids64_) dist2_->append(v.dist2, nk);
  if (counts_) counts_->append(v.counts, part.n);
  for (std::size_t i = 0; i < part.n; ++i) found_ += static_cast<std::size_t>(v.counts[i]);
}

void KnnOutputs::append_ids_and_dist2(const void* ids, const float* dist2, std::size_t items) {
  if (ids == ids_->next() && dist2 == dist2_->next()) {  // stored in place by the search: no copy
    ids_->append(ids, items);
    dist2_->append(dist2, items);
    return;
  }
  // Two files, two threads: the copy into the page cache (most of a large slice's write) runs on
  // both cores instead of one.
  detail::parallel_tasks(2, [&](std::size_t t) {
    if (t == 0) ids_->append(ids, items);
    else dist2_->append(dist2, items);
  });
}
void KnnOutputs::append(const KnnResult64& part) { append_part(part); }

template <typename Part>
void KnnOutputs::append_part(const Part& part) {
  if (ids64_) {
    std::vector<std::int64_t> tmp;
    append_ids_and_dist2(ids_as(part.ids, part.ids.size(), tmp), part.dist2.data(), part.ids.size());
  } else {
    std::vector<std::int32_t> tmp;
    append_ids_and_dist2(ids_as(part.ids, part.ids.size(), tmp), part.dist2.data(), part.ids.size());
  }
  if (counts_) counts_->append(part.counts.data(), part.counts.size());
  for (auto c : part.counts) found_ += static_cast<std::size_t>(c);
}

void KnnOutputs::commit() {
  ids_->commit();
  dist2_->commit();
  if (counts_) counts_->commit();
}

RadiusOutputs::RadiusOutputs(const Args& args, std::size_t n, bool ids64) : ids64_(ids64) {
  offsets_ = std::make_unique<ArrayOutput>(args.str("out-offsets"), "<i8", 8, static_cast<std::int64_t>(n + 1), 0);
  ids_ = std::make_unique<ArrayOutput>(args.str("out-ids"), ids64 ? "<i8" : "<i4", ids64 ? 8 : 4, -1, 0);
  dist2_ = std::make_unique<ArrayOutput>(args.str("out-dist2"), "<f4", 4, -1, 0);
  if (args.has("out-counts"))
    counts_ = std::make_unique<ArrayOutput>(args.str("out-counts"), "<i4", 4, static_cast<std::int64_t>(n), 0);
  const std::int64_t zero = 0;
  offsets_->append(&zero, 1);
}

void RadiusOutputs::append(const RadiusResult& part) { append_part(part); }
void RadiusOutputs::append(const RadiusResult64& part) { append_part(part); }

template <typename Part>
void RadiusOutputs::append_part(const Part& part) {
  std::vector<std::int64_t> offs(part.n);
  std::vector<std::int32_t> counts(counts_ ? part.n : 0);
  for (std::size_t i = 0; i < part.n; ++i) {
    offs[i] = base_ + part.offsets[i + 1];
    if (counts_) counts[i] = static_cast<std::int32_t>(part.count(i));
  }
  offsets_->append(offs.data(), offs.size());
  if (ids64_) {
    std::vector<std::int64_t> tmp;
    ids_->append(ids_as(part.ids, part.total(), tmp), part.total());
  } else {
    std::vector<std::int32_t> tmp;
    ids_->append(ids_as(part.ids, part.total(), tmp), part.total());
  }
  dist2_->append(part.dist2.data(), part.total());
  if (counts_) counts_->append(counts.data(), counts.size());
  base_ += static_cast<std::int64_t>(part.total());
  truncated_ += part.truncated_queries;
}

void RadiusOutputs::commit() {
  offsets_->commit();
  ids_->commit();
  dist2_->commit();
  if (counts_) counts_->commit();
}

}  // namespace bhcl::cli
