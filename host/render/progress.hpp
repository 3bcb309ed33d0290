// A one-line terminal progress bar with elapsed time and time left, on stderr. Quiet when stderr
// is not a terminal or when disabled (--quiet), so logs and tests stay clean.
#pragma once

#include <chrono>
#include <string>

namespace bhcl::render {

class Progress {
 public:
  Progress(std::string label, bool enabled);
  ~Progress();
  // fraction in [0, 1]; redraws at most 10 times a second (and always at 1).
  void update(double fraction, const std::string& note = {});
  void finish();
  bool enabled() const { return enabled_; }
  static bool stderr_is_terminal();

 private:
  std::string label_;
  bool enabled_;
  bool finished_ = false;
  double drawn_ = -1;  // the fraction last drawn
  std::chrono::steady_clock::time_point start_, last_;
};

std::string format_duration(double seconds);  // "1:05", "1:02:03"

}  // namespace bhcl::render
