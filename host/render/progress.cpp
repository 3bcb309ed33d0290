#include "progress.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace bhcl::render {

bool Progress::stderr_is_terminal() { return isatty(2) == 1; }

std::string format_duration(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  long t = std::lround(s);
  char b[32];
  if (t >= 3600) std::snprintf(b, sizeof b, "%ld:%02ld:%02ld", t / 3600, (t / 60) % 60, t % 60);
  else std::snprintf(b, sizeof b, "%ld:%02ld", t / 60, t % 60);
  return b;
}

Progress::Progress(std::string label, bool enabled)
    : label_(std::move(label)), enabled_(enabled && stderr_is_terminal()),
      start_(std::chrono::steady_clock::now()), last_(start_ - std::chrono::seconds(1)) {}

Progress::~Progress() { finish(); }

void Progress::update(double f, const std::string& note) {
  if (!enabled_ || finished_) return;
  auto now = std::chrono::steady_clock::now();
  f = std::clamp(f, 0.0, 1.0);
  if (f < 1.0 && now - last_ < std::chrono::milliseconds(100)) return;
  last_ = now;
  drawn_ = f;
  double elapsed = std::chrono::duration<double>(now - start_).count();
  double left = f > 0 ? elapsed * (1.0 - f) / f : NAN;
  const int width = 30;
  int filled = static_cast<int>(f * width);
  std::string bar(static_cast<std::size_t>(filled), '#');
  bar.resize(width, '-');
  std::fprintf(stderr, "\r%-14s [%s] %5.1f%%  %s elapsed, %s left %s\033[K", label_.c_str(),
               bar.c_str(), 100.0 * f, format_duration(elapsed).c_str(),
               f > 0 ? format_duration(left).c_str() : "?", note.c_str());
  std::fflush(stderr);
}

void Progress::finish() {
  if (!enabled_ || finished_) return;
  if (drawn_ < 1.0) update(1.0);
  finished_ = true;
  std::fprintf(stderr, "\n");
}

}  // namespace bhcl::render
