#define DOCTEST_CONFIG_IMPLEMENT
#include <doctest/doctest.h>

#include <cstdlib>
#include <string>

int main(int argc, char** argv) {
  // The library's program binaries of the tests' own runtimes in the build tree, not in the
  // user's ~/.cache (the bhcl the CLI tests run does the same for itself); a caller's choice kept.
  if (const char* set = std::getenv("BHCL_CACHE_DIR"); !(set && *set))
    setenv("BHCL_CACHE_DIR", (std::string(BHCL_TEST_TMP_DIR) + "/../../program-cache").c_str(), 1);
  doctest::Context context(argc, argv);
  return context.run();
}
