// Locale-free number text (issue 38): every number the library, the CLI and the bindings read or
// write goes through these, never strtod / stod / stoul / printf("%g"), whose decimal point is the
// C locale's (a process that called setlocale(LC_ALL, "de_DE.UTF-8"), as GUI toolkits do, reads
// "8.0" as 8 and stops at the '.', and writes 8.5 as "8,5"), and whose out-of-range cases throw
// std::out_of_range with the function's name ("stoul") as the message. std::from_chars and
// std::to_chars never look at the locale.
#pragma once

#include <charconv>
#include <cmath>
#include <cstdint>
#include <string>
#include <string_view>
#include <system_error>

namespace bhcl::detail {

enum class NumberParse { Ok, NotNumber, OutOfRange };

// The whole of s as a decimal real number, as strtod reads it in the C locale: an optional sign
// (from_chars takes no '+'), digits with '.', an exponent, "inf", "infinity" or "nan" in any case,
// and hexadecimal "0x1.8p3". Out of the double range: OutOfRange, out set as strtod would (+-inf
// for a too-large magnitude, +-0 for a too-small one), so that callers may refuse or use it.
inline NumberParse parse_double(std::string_view s, double& out) {
  bool neg = false;
  if (!s.empty() && (s[0] == '+' || s[0] == '-')) {
    neg = s[0] == '-';
    s.remove_prefix(1);
  }
  if (s.empty() || s[0] == '+' || s[0] == '-') return NumberParse::NotNumber;
  std::chars_format fmt = std::chars_format::general;
  if (s.size() > 2 && s[0] == '0' && (s[1] == 'x' || s[1] == 'X')) {
    s.remove_prefix(2);
    fmt = std::chars_format::hex;
    if (s.empty() || s[0] == '+' || s[0] == '-') return NumberParse::NotNumber;
  }
  double v = 0;
  const auto r = std::from_chars(s.data(), s.data() + s.size(), v, fmt);
  if (r.ptr != s.data() + s.size() || (r.ec != std::errc() && r.ec != std::errc::result_out_of_range))
    return NumberParse::NotNumber;
  if (r.ec == std::errc::result_out_of_range) {
    // Which side: the exponent's sign (an overflow has a large positive one, an underflow a
    // negative one; a mantissa of many digits alone never leaves the range).
    const std::size_t e = s.find_first_of(fmt == std::chars_format::hex ? "pP" : "eE");
    const bool tiny = e != std::string_view::npos && e + 1 < s.size() && s[e + 1] == '-';
    out = tiny ? (neg ? -0.0 : 0.0) : (neg ? -HUGE_VAL : HUGE_VAL);
    return NumberParse::OutOfRange;
  }
  out = neg ? -v : v;
  return NumberParse::Ok;
}

// The whole of s as a decimal integer (an optional sign; '+' accepted as strtoll does).
template <typename Int>
NumberParse parse_integer(std::string_view s, Int& out) {
  if (s.size() > 1 && s[0] == '+' && s[1] != '-' && s[1] != '+') s.remove_prefix(1);
  if (s.empty()) return NumberParse::NotNumber;
  Int v{};
  const auto r = std::from_chars(s.data(), s.data() + s.size(), v, 10);
  if (r.ptr != s.data() + s.size() && r.ec == std::errc()) return NumberParse::NotNumber;
  if (r.ec == std::errc::result_out_of_range) {
    // from_chars stops at the end of the digits: out of range only when they are all digits.
    return r.ptr == s.data() + s.size() ? NumberParse::OutOfRange : NumberParse::NotNumber;
  }
  if (r.ec != std::errc()) return NumberParse::NotNumber;
  out = v;
  return NumberParse::Ok;
}

// The shortest text that reads back to exactly x (to_chars' round-trip form), '.'-separated.
inline std::string format_double(double x) {
  char b[64];
  const auto r = std::to_chars(b, b + sizeof b, x);
  return std::string(b, r.ptr);
}
inline std::string format_float(float x) {
  char b[64];
  const auto r = std::to_chars(b, b + sizeof b, x);
  return std::string(b, r.ptr);
}
// printf's "%.Ng" (N significant digits), '.'-separated whatever the locale.
inline std::string format_general(double x, int digits) {
  char b[64];
  const auto r = std::to_chars(b, b + sizeof b, x, std::chars_format::general, digits);
  return std::string(b, r.ptr);
}

}  // namespace bhcl::detail
