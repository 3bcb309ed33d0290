// Point files, N x 3 (x y z per point), in the formats point clouds come in:
//  - raw:  little-endian float32 x y z triples, no header; N = size / 12 (.f32, .bin, .raw)
//  - text: one point per line, x y z separated by white space or commas; '#' starts a comment,
//          blank lines are skipped (.txt, .xyz, .csv, .asc, .pts)
//  - PLY:  ASCII, binary little or big endian; the vertex element's x, y, z properties as float
//          or double; other properties and elements are skipped (.ply)
//  - NPY:  NumPy arrays of float32 or float64, shape (N, 3), C order (.npy)
// The format comes from the file name's extension, or, without a known one, from the content
// (the PLY and NPY magic, text that is all printable, raw otherwise). A file whose content
// contradicts its format (text or a PLY file named .f32, a PLY without x/y/z, an NPY of int32) is
// refused with one line naming the file and what is wrong, never misread. Coordinates are read as
// float; a double that does not fit a float is refused.
// Result files: raw int32 / float32, n x k row-major, or NPY when the name ends in .npy.
#pragma once

#include <cstddef>
#include <cstdint>
#include <initializer_list>
#include <string>
#include <string_view>
#include <vector>

namespace bhcl {

enum class PointFormat { Auto, Raw, Text, Ply, Npy };

const char* point_format_name(PointFormat f);  // "auto", "raw float32", "text", "PLY", "NPY"

// The format of a file named `path` (Auto when its extension says nothing).
PointFormat point_format_from_name(const std::string& path);
// The format the bytes look like: PLY or NPY by their magic, text when every byte is printable
// text with a digit, raw otherwise.
PointFormat sniff_point_format(const void* data, std::size_t size);

// Reads a point file in any of the formats above. Throws bhcl::Error naming the path for a
// missing/unreadable file, a malformed or contradicting file, or (when require_finite) the first
// point with a NaN/Inf coordinate. An empty file (or zero points) gives an empty vector.
// A file that declares more than max_points points (raw: by its size; NPY, PLY: by its header)
// is refused before its body is read (0: no limit). The default is the index range, N <= 2^31 - 2.
std::vector<float> read_points_file(const std::string& path, bool require_finite = true,
                                    std::size_t max_points = 0x7ffffffe);

// The point count a file declares before its body is read (raw: by its size; NPY, PLY: by its
// header), read from its first 4 KiB; 0 where it does not say (text) or the file cannot be read.
// Not checked against the body: a size hint for what is made ahead of reading it.
std::uint64_t declared_point_count(const std::string& path) noexcept;

// float64 kept: the file's coordinates as it holds them (a text file's decimals, a float64 PLY or
// NPY in double; float32 sources widened), after the same checks as read_points_file, whose
// float copy goes to *as_float when given.
std::vector<double> read_points_file_f64(const std::string& path, std::vector<float>* as_float = nullptr,
                                         bool require_finite = true, std::size_t max_points = 0x7ffffffe);

// Coordinates stored in float32 relative to an origin computed in double precision (bhcl's point
// files; the Python package does the same for float64 arrays): the centre of the points' box,
// rounded to a float value, where that gains precision (the largest |coordinate| is more than 4
// times the largest |coordinate - centre|: georeferenced data, UTM at 4.3e6 m), else 0. Queries
// are taken relative to the same origin; distances are differences, so they stay in caller units.
struct Recentring {
  double origin[3] = {0, 0, 0};
  bool recentred = false;
  double max_abs_relative = 0;  // the largest |stored coordinate| (relative_points' inputs)
  double float32_step = 0;      // the float spacing there: the rounding left is half of it
};
Recentring choose_origin(const double* xyz, std::size_t n);
// xyz - origin in double, rounded once to float (a value beyond the float range refused naming
// `what`); widens r.max_abs_relative and r.float32_step over what it converted.
std::vector<float> relative_points(const double* xyz, std::size_t n, Recentring& r, const std::string& what);

// Parses the bytes of a point file (what read_points_file does after reading); `what` names the
// source in errors and, by its extension, picks the format (else the content does). The fuzz
// target drives this.
std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                bool require_finite = true);
// The same in a given format (Auto: from `what`'s extension, else sniffed).
std::vector<float> parse_points(const void* data, std::size_t size, const std::string& what,
                                PointFormat format, bool require_finite);

// The size of the input file `path`, after checking that it is a regular file: a directory, a
// FIFO, a socket or a device (/dev/zero) is refused with a bhcl::Error naming the file and `what`
// it should have held, before anything is opened (a FIFO's open would wait for a writer).
std::uint64_t regular_file_size(const std::string& path, const std::string& what);

// Writes `parts` one after the other to `path`, replacing it atomically. Every output of the
// library, of bhcl and of the renderer goes through here: the bytes go to a temporary beside the
// target (".NAME.tmp.PID.N" in the same directory), are flushed to the disk (fsync) and checked,
// then the temporary is renamed over `path`. A failure (a full disk, a size limit, no
// permission) is a bhcl::Error naming the file, `what` it held and the system's reason
// (strerror); the temporary is removed and the old file stays intact, never a short file and
// success. A kill during the write leaves the old file too (and at most the temporary). A path
// that names a device or FIFO (/dev/stdout) is written in place.
void write_file(const std::string& path, std::initializer_list<std::string_view> parts,
                const std::string& what);

// Writes raw float32 x y z triples.
void write_points_file(const std::string& path, const std::vector<float>& xyz);

// Writes raw bytes; throws bhcl::Error naming the path on failure.
void write_raw_file(const std::string& path, const void* data, std::size_t bytes);

// Writes a rows x cols array (C order) as NPY version 1.0 ('<f4', '<i4', '<i8').
// The header of an NPY (version 1.0) file of a C-order array of `rows` x `cols` (cols 0: a
// vector) items of numpy type `descr` ("<f4", "<i4", ...): magic, version, length and the dict,
// padded with spaces to a multiple of 64 bytes, or to `pad_to` bytes when given (a header that
// replaces one written before; it must fit).
std::string npy_header(const char* descr, std::uint64_t rows, std::size_t cols, std::size_t pad_to = 0);
void write_npy_file(const std::string& path, const float* data, std::size_t rows, std::size_t cols);
void write_npy_file(const std::string& path, const std::int32_t* data, std::size_t rows,
                    std::size_t cols);
void write_npy_file(const std::string& path, const std::int64_t* data, std::size_t rows,
                    std::size_t cols);
// A result array: NPY (rows x cols; cols == 0 for a 1-D array of rows) when the path ends in
// .npy, raw bytes otherwise.
void write_array_file(const std::string& path, const float* data, std::size_t rows, std::size_t cols);
void write_array_file(const std::string& path, const std::int32_t* data, std::size_t rows,
                      std::size_t cols);
void write_array_file(const std::string& path, const std::int64_t* data, std::size_t rows,
                      std::size_t cols);

}  // namespace bhcl
