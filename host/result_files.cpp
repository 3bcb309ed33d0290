#include "result_files.hpp"

#include <cctype>
#include <cstdint>
#include <cstring>
#include <exception>
#include <mutex>
#include <new>
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

// Outputs of at least this size are written with O_DIRECT (issue 37). Smaller ones stay mapped:
// bhcl knn, Cornell 1M, AVX-512, 2 threads, alternating with the mapped path (main), the whole
// process with direct outputs forced at 100k x 10 (4 MB a file, one slice: its write cannot
// overlap a next search) 1.02 of main's, its search wall 1.13; at 100k x 50 (20 MB) 0.98 / 1.00;
// at 1M x 10 (40 MB) 0.84 / 0.88; at 1M x 50 (200 MB) 0.90 / 0.94 (bench/results/e2e/direct_output_h37f.md).
constexpr std::size_t kDirectBytes = std::size_t(32) << 20;

// BHCL_DIRECT_OUTPUT: unset: direct outputs (O_DIRECT) for known lengths of 32 MiB or more; "0":
// never (the mapped path); "1": every known length (the tests' small outputs).
int direct_output_mode() {
  const char* e = std::getenv("BHCL_DIRECT_OUTPUT");
  if (!e || !*e) return -1;
  return e[0] == '0' ? 0 : 1;
}

char* aligned_bytes(std::size_t bytes, std::size_t align) {
  void* p = nullptr;
  if (::posix_memalign(&p, align, (bytes + align - 1) / align * align) != 0) throw std::bad_alloc();
  return static_cast<char*>(p);
}

bool is_npy(const std::string& path) {
  if (path.size() < 4) return false;
  std::string e = path.substr(path.size() - 4);
  for (char& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e == ".npy";
}
}  // namespace

bool direct_output_expected(std::uint64_t bytes) {
  const int mode = direct_output_mode();
  return bytes > 0 && (mode == 1 || (mode < 0 && bytes >= kDirectBytes));
}

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
  const std::size_t bytes = rows_ >= 0 ? static_cast<std::size_t>(rows_) * (cols_ ? cols_ : 1) * item_ : 0;
  if (bytes > 0 && direct_output_expected(h.size() + bytes)) open_direct(h, bytes);
  if (!align_ && !map_known_length(h)) file_.write(h.data(), h.size());
}

void ArrayOutput::open_direct(const std::string& head, std::size_t bytes) {
  const std::size_t align = file_.open_direct(head.size() + bytes);
  if (!align || head.size() >= align || align > DirectBuffer::kAlign) return;  // written as before
  align_ = align;
  carry_.reset(aligned_bytes(align, align));
  std::memcpy(carry_.get(), head.data(), head.size());
  carry_len_ = head.size();
  pos_ = head.size();
}

void ArrayOutput::append_direct(char* rows, std::size_t items) {
  const std::uint64_t total = static_cast<std::uint64_t>(rows_) * (cols_ ? cols_ : 1);
  if (!align_ || items_ + items > total)
    throw Error(file_.path() + ": internal error: a direct append of " + std::to_string(items_ + items) +
                " items of " + std::to_string(total));
  const std::size_t bytes = items * item_;
  char* const start = rows - carry_len_;  // the carried part of a block before the rows
  if (reinterpret_cast<std::uintptr_t>(start) % align_ != 0)
    throw Error(file_.path() + ": internal error: direct rows not placed after their block's carried bytes");
  std::memcpy(start, carry_.get(), carry_len_);
  const std::size_t all = carry_len_ + bytes, whole = all / align_ * align_;
  if (whole) file_.write_direct(pos_ - carry_len_, start, whole);
  carry_len_ = all - whole;
  std::memcpy(carry_.get(), start + whole, carry_len_);
  pos_ += bytes;
  items_ += items;
  if (items_ == total) {  // the last rows: the tail block padded, then the file cut to its size
    if (carry_len_) {
      std::memset(carry_.get() + carry_len_, 0, align_ - carry_len_);
      file_.write_direct(pos_ - carry_len_, carry_.get(), align_);
    }
    file_.truncate(pos_);
  }
}

namespace {

// A direct buffer's bytes for `bytes` of rows: room for the carried block before them and the
// padding after; on 2 MiB boundaries where advised MADV_HUGEPAGE (BHCL_DIRECT_THP=0: neither).
bool direct_thp() {
  const char* e = std::getenv("BHCL_DIRECT_THP");
  return !(e && e[0] == '0');
}
std::size_t direct_len(std::size_t bytes, bool thp) {
  constexpr std::size_t huge = std::size_t(2) << 20;
  return thp ? (DirectBuffer::kAlign + bytes + DirectBuffer::kAlign + huge - 1) / huge * huge
             : DirectBuffer::kAlign + bytes + DirectBuffer::kAlign;
}
char* make_direct(std::size_t len, bool thp) {
  char* p = aligned_bytes(len, thp ? std::size_t(2) << 20 : DirectBuffer::kAlign);
  if (thp) {
    (void)::madvise(p, len, MADV_HUGEPAGE);
    (void)::madvise(p, len, MADV_POPULATE_WRITE);
  }
  return p;
}

// prefault_direct_buffers' buffers, taken by DirectBuffer::reserve.
struct DirectPool {
  std::mutex m;
  std::vector<std::pair<char*, std::size_t>> free;  // (memory, len)
  int taken = 0;                                    // reserves it served
  ~DirectPool() {
    for (auto& b : free) std::free(b.first);
  }
};
DirectPool& direct_pool() {
  static DirectPool pool;
  return pool;
}

}  // namespace

int direct_buffers_taken_ahead() {
  std::lock_guard<std::mutex> lock(direct_pool().m);
  return direct_pool().taken;
}

void prefault_direct_buffers(std::size_t bytes, int count) {
  const bool thp = direct_thp();
  const std::size_t len = direct_len(bytes, thp);
  for (int i = 0; i < count; ++i) {
    char* p = make_direct(len, thp);
    std::lock_guard<std::mutex> lock(direct_pool().m);
    direct_pool().free.emplace_back(p, len);
  }
}

void DirectBuffer::reserve(std::size_t bytes) {
  if (bytes <= cap_ && mem_) return;
  // Made present here (timed as the write stage) unless prefault_direct_buffers made one of at
  // least this size ahead. In 2 MiB pages: the kernel stores each row at its caller's row, i.e.
  // at random places, and in 4 KiB pages it was 1.15-1.25x the mapped path's (whose file pages
  // are 2 MiB folios); with them 0.76 (1M x 50, Cornell, AVX-512, 2 threads, alternating
  // processes, median of 4). BHCL_DIRECT_THP=0: 4 KiB pages (the experiment's other arm).
  const bool thp = direct_thp();
  const std::size_t len = direct_len(bytes, thp);
  {
    std::lock_guard<std::mutex> lock(direct_pool().m);
    auto& free = direct_pool().free;
    auto best = free.end();
    for (auto it = free.begin(); it != free.end(); ++it)
      if (it->second >= len && (best == free.end() || it->second < best->second)) best = it;
    if (best != free.end()) {
      mem_.reset(best->first);
      free.erase(best);
      ++direct_pool().taken;
      cap_ = bytes;
      return;
    }
  }
  mem_.reset(make_direct(len, thp));
  cap_ = bytes;
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
  if (align_) {  // direct: copied through an aligned staging buffer, 4 MiB at a time
    const std::size_t chunk = std::size_t(4) << 20, per = chunk / item_;
    if (!staging_) staging_.reset(aligned_bytes(DirectBuffer::kAlign + chunk + DirectBuffer::kAlign, DirectBuffer::kAlign));
    const char* p = static_cast<const char*>(data);
    for (std::size_t done = 0; done < items;) {
      const std::size_t m = std::min(per, items - done);
      char* rows = staging_.get() + carry_len_;
      std::memcpy(rows, p + done * item_, m * item_);
      append_direct(rows, m);
      done += m;
    }
    return;
  }
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
  total_items_ = static_cast<std::uint64_t>(n) * cols;
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

KnnRowsView KnnOutputs::rows_for(const KnnSlice& part) {
  if (!direct()) return rows_at_next(part, true);
  KnnRowsView v = part.view();
  const std::size_t bytes = part.n * static_cast<std::size_t>(part.k) * 4;
  DirectBuffer &ib = ids_buf_[buf_], &db = dist2_buf_[buf_];
  if (bytes > ib.capacity() || ib.capacity() == 0) {
    // The two buffers' rows (the slice's own rows were counted by KnnSlice::reserve).
    check_result_memory(part.n, part.k, false, 2, "bhcl knn");
    ib.reserve(bytes);
    db.reserve(bytes);
  }
  // Each file's rows placed after room for the part of a block the previous slices left over.
  v.ids = reinterpret_cast<std::int32_t*>(ib.rows(ids_->direct_lead(items_)));
  v.dist2 = reinterpret_cast<float*>(db.rows(dist2_->direct_lead(items_)));
  handed_items_ = part.n * static_cast<std::size_t>(part.k);
  return v;
}

void KnnOutputs::wait_direct() {
  // Both waited before either rethrows: no write outlives this call.
  std::exception_ptr err;
  for (std::future<void>* f : {&ids_write_, &dist2_write_}) {
    if (!f->valid()) continue;
    try {
      f->get();
    } catch (...) {
      if (!err) err = std::current_exception();
    }
  }
  if (err) std::rethrow_exception(err);
}

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
  KnnRowsView v = rows_at_next(part, false);
  const bool handed = handed_items_ == nk;
  handed_items_ = ~std::size_t(0);
  if (direct() && handed && nk > 0) {
    // The rows the search stored in this slice's buffers (rows_for): their writes started on two
    // threads after the previous slice's finished; the last slice's waited for here.
    char *ids = ids_buf_[buf_].rows(ids_->direct_lead(items_)), *d2 = dist2_buf_[buf_].rows(dist2_->direct_lead(items_));
    wait_direct();
    ids_write_ = std::async(std::launch::async, [this, ids, nk] { ids_->append_direct(ids, nk); });
    dist2_write_ = std::async(std::launch::async, [this, d2, nk] { dist2_->append_direct(d2, nk); });
    buf_ ^= 1;
    items_ += nk;
    if (items_ == total_items_) wait_direct();
    v = part.view();
  } else if (direct()) {
    // Rows not in this output's buffers (rows_for not asked): copied through append's staging.
    wait_direct();
    append_ids_and_dist2(v.ids, v.dist2, nk);
    items_ += nk;
  } else if (ids64_) {
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
  wait_direct();
  items_ += part.ids.size();
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
  wait_direct();
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
