// Point-file formats, shared by core/io.cpp (reading, format choice), core/io_parse.cpp (the
// parsers) and core/io_write.cpp (writing): internal to the library.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace bhcl::io_detail {

[[noreturn]] void fail(const std::string& what, const std::string& msg);
std::string lower_extension(const std::string& path);
bool is_ply(const void* data, std::size_t size);
bool is_npy(const void* data, std::size_t size);
// Every byte printable ASCII or white space, and at least one digit.
bool looks_like_text(const void* data, std::size_t size);
// UTF-16 text: a byte order mark (FF FE or FE FF), or, without one, printable ASCII in every
// other byte with zeros between (checked over the first 256 bytes).
bool looks_like_utf16(const unsigned char* b, std::size_t size);

// read_points_file_f64: while set, every double coordinate a parser reads is also kept here at
// its value index (the float copy is what the parsers return; a float source fills none).
extern thread_local std::vector<double>* t_wide;
// A double coordinate as float: refused (not turned into inf) when it does not fit.
float to_float(double v, const std::string& what, std::size_t value_index);
void check_finite(const std::vector<float>& xyz, const std::string& what);

// The parsers: x y z float per point, `what` naming the source in errors.
std::vector<float> parse_raw(const void* data, std::size_t size, const std::string& what);
std::vector<float> parse_text(const void* data, std::size_t size, const std::string& what);
std::vector<float> parse_ply(const void* data, std::size_t size, const std::string& what);
std::vector<float> parse_npy(const void* data, std::size_t size, const std::string& what);

// An NPY file of rows x cols items (cols 0: a 1-D array) of dtype `descr`, written atomically.
void write_npy(const std::string& path, const void* data, const char* descr, std::size_t item,
               std::size_t rows, std::size_t cols);

}  // namespace bhcl::io_detail
