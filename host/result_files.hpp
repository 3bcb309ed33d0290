// bhcl knn's output files written as the slices of a query call finish (issue 22): each array
// goes to its own AtomicFile (a temporary beside the target, renamed over it at commit), so that
// the tool never holds a second copy of the whole result, and a failure anywhere (a full disk, a
// search that throws) removes every temporary: no partial output, the old files intact, and the
// error names the file and the system's reason. NPY files get their header first; a radius
// result's length is known only at the end, so its header is rewritten then (same length).
#pragma once

#include <cstdint>
#include <cstdlib>
#include <future>
#include <memory>
#include <string>

#include "blockhash_cl/atomic_file.hpp"
#include "blockhash_cl/knn.hpp"

namespace bhcl::cli {

class Args;

// One array: NPY when the path ends in .npy ('<f4', '<i4', '<i8'), raw bytes otherwise. rows < 0:
// not known until commit (NPY: the header is rewritten then). A known length is the file mapped
// where it can be (AtomicFile::map_append): appends are copies into the page cache without a
// write(), and none where the rows were stored at their place already (next()).
class ArrayOutput {
 public:
  ArrayOutput(const std::string& path, const char* descr, std::size_t item, std::int64_t rows, std::size_t cols);
  void append(const void* data, std::size_t items);
  // Where the next items' bytes go in the mapped file (null: not mapped): a search that stores
  // its rows there has nothing left for append() to copy.
  void* next() const { return mapped_ ? mapped_ + items_ * item_ : nullptr; }
  // The pages of the next `items` made present and writable, in order on this thread
  // (MADV_POPULATE_WRITE): the search stores its rows in dispatch order, i.e. at random places,
  // and its threads' faults on a shared file mapping contend (1M x 10: the kernel 10-30 % slower
  // when it took them itself). Nothing where not mapped.
  void populate_next(std::size_t items) const;
  // Direct output (O_DIRECT, issue 37): the block alignment its writes keep, 0 where the file is
  // written through the page cache (mapped or write()). Chosen at construction for a known length
  // of 32 MiB or more where the file system takes O_DIRECT (BHCL_DIRECT_OUTPUT=0: never, =1: any
  // known length). The NPY header is the first block's start; the rows follow in whole blocks, the
  // part of a block left over carried to the next append; the last rows' append writes the tail
  // padded and cuts the file to its size, so commit() is the flush and the rename only.
  std::size_t direct_align() const { return align_; }
  // Where the rows after `items` written lie in their block: the bytes of it before them.
  std::size_t direct_lead(std::uint64_t items) const { return align_ ? (header_bytes_ + items * item_) % align_ : 0; }
  // The next `items` from `rows`, a direct output's: `rows` lies direct_lead(items written) bytes
  // after an aligned address, those bytes writable, and the memory up to the next aligned address
  // after its last byte writable (DirectBuffer::rows). Those bytes are overwritten. On any thread,
  // one call at a time.
  void append_direct(char* rows, std::size_t items);
  void commit();

 private:
  std::string header(std::uint64_t rows) const;
  // The rows' bytes (after `head`, the NPY header or nothing) mapped where the length is known
  // and the file can be mapped, the header stored there; false: nothing done.
  bool map_known_length(const std::string& head);
  AtomicFile file_;
  std::string descr_;
  std::size_t item_, cols_;
  std::int64_t rows_;
  std::uint64_t items_ = 0;
  bool npy_;
  std::size_t header_bytes_ = 0;
  char* mapped_ = nullptr;  // the array's first item in the mapped file
  // Direct output: the part of a block not written yet (carry_len_ bytes; at first the header),
  // and the file's length so far (pos_; pos_ - carry_len_ is aligned).
  void open_direct(const std::string& head, std::size_t bytes);
  std::size_t align_ = 0;
  std::unique_ptr<char, decltype(&std::free)> carry_{nullptr, &std::free};
  std::size_t carry_len_ = 0;
  std::uint64_t pos_ = 0;
  std::unique_ptr<char, decltype(&std::free)> staging_{nullptr, &std::free};  // append()'s copies
};

// Whether an output file of `bytes` (header and rows) will be written with O_DIRECT
// (BHCL_DIRECT_OUTPUT and the size threshold; ArrayOutput's rule): a file system that refuses
// O_DIRECT is known only when the file is opened.
bool direct_output_expected(std::uint64_t bytes);

// Memory for a direct output's rows: `bytes` at rows(lead), `lead` bytes after its aligned start
// (room for the carried part of a block: ArrayOutput::append_direct), and room for the padding
// of the last block after. Never filled; on 2 MiB boundaries, advised MADV_HUGEPAGE and made
// present at reserve, or taken there from prefault_direct_buffers' (BHCL_DIRECT_THP=0: 4 KiB
// pages, first touched by the search).
class DirectBuffer {
 public:
  void reserve(std::size_t bytes);
  char* rows(std::size_t lead) const { return mem_.get() + lead; }  // lead < kAlign
  std::size_t capacity() const { return cap_; }
  static constexpr std::size_t kAlign = 4096;

 private:
  std::unique_ptr<char, decltype(&std::free)> mem_{nullptr, &std::free};
  std::size_t cap_ = 0;
};

// Direct buffers of `bytes` rows' bytes each made present ahead of a search, on a thread with
// nothing else to do (bhcl knn: beside reading its inputs); DirectBuffer::reserve takes one of at
// least its size from them before it makes its own.
void prefault_direct_buffers(std::size_t bytes, int count);
// How many DirectBuffer::reserve calls took one of them (bhcl knn's stats: output_buffers_ahead).
int direct_buffers_taken_ahead();

// A slice's kNN rows in memory kept across the slices of a run and never filled before the search
// writes it (SearchIndex::query_into): a KnnResult's resize is a single-threaded pass over every
// page first. Sized for the largest slice at the first use.
class KnnSlice {
 public:
  void reserve(std::size_t rows, int k, bool examined);
  KnnRowsView view() const { return {ids_.get(), dist2_.get(), counts_.get(), examined_.get()}; }
  std::size_t n = 0;  // the rows of the current slice
  int k = 0;

 private:
  std::unique_ptr<std::int32_t[]> ids_, counts_, examined_;
  std::unique_ptr<float[]> dist2_;
  std::size_t capacity_ = 0;
};

// --out-ids, --out-dist2 and --out-counts of a kNN call of n queries and k. ids64: the ids are
// written as int64 ('<i8', 8 bytes raw), for ids past 2^31 (bhcl knn --distributed); else int32.
class KnnOutputs {
 public:
  KnnOutputs(const Args& args, std::size_t n, int k, bool ids64 = false);
  void append(const KnnResult& part);  // the next rows, in order
  void append(const KnnResult64& part);  // the same with int64 ids (each fits when !ids64)
  void append(const KnnSlice& part);
  // The rows the search of the next slice writes: ids and dist2 at their places in the mapped
  // files where they are mapped (int32 ids; their pages made present first), else the slice's own
  // memory; counts and examined always the slice's.
  // Direct outputs (ids and dist2 both): the rows land in one of two DirectBuffers, and each
  // slice's O_DIRECT writes run on threads beside the next slice's search (append waits for the
  // previous slice's; the last slice's append for its own, so that the call's wall holds them).
  KnnRowsView rows_for(const KnnSlice& part);
  bool direct() const { return !ids64_ && ids_->direct_align() && dist2_->direct_align(); }
  void commit();
  std::size_t found() const { return found_; }

 private:
  template <typename Part>
  void append_part(const Part& part);
  void append_ids_and_dist2(const void* ids, const float* dist2, std::size_t items);
  KnnRowsView rows_at_next(const KnnSlice& part, bool populate) const;
  void wait_direct();
  std::unique_ptr<ArrayOutput> ids_, dist2_, counts_;
  bool ids64_ = false;
  std::size_t found_ = 0;
  std::uint64_t items_ = 0, total_items_ = 0;
  // The futures declared last: destroyed first, each waiting for its write (std::async's), so no
  // write outlives its buffer or its file.
  DirectBuffer ids_buf_[2], dist2_buf_[2];
  int buf_ = 0;  // the buffer the next slice's rows land in
  std::size_t handed_items_ = ~std::size_t(0);  // the items rows_for's view holds (none: ~0)
  std::future<void> ids_write_, dist2_write_;
};

// --out-offsets, --out-ids, --out-dist2 and --out-counts of a radius call of n queries.
class RadiusOutputs {
 public:
  RadiusOutputs(const Args& args, std::size_t n, bool ids64 = false);  // ids64 as KnnOutputs'
  void append(const RadiusResult& part);  // the next queries' slices, in order
  void append(const RadiusResult64& part);
  void commit();
  std::size_t total() const { return static_cast<std::size_t>(base_); }
  std::size_t truncated_queries() const { return truncated_; }

 private:
  template <typename Part>
  void append_part(const Part& part);
  std::unique_ptr<ArrayOutput> offsets_, ids_, dist2_, counts_;
  bool ids64_ = false;
  std::int64_t base_ = 0;
  std::size_t truncated_ = 0;
};

}  // namespace bhcl::cli
