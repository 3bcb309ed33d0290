// Errors thrown by blockhash_cl. Every error says what failed and where: an OpenCL call carries
// the call's name and the error's name; a failed kernel build carries the options and the log.
#pragma once

#include <stdexcept>
#include <string>

namespace bhcl {

// Base of everything the library throws: bad input, bad parameters, unreadable files.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

// An OpenCL call returned an error code.
class ClError : public Error {
 public:
  ClError(int code, const std::string& call, const std::string& context);
  int code() const { return code_; }
  const std::string& call() const { return call_; }

 private:
  int code_;
  std::string call_;
};

// A kernel program failed to build: what() holds the file, the options and the build log.
class BuildError : public ClError {
 public:
  BuildError(int code, const std::string& file, const std::string& options, const std::string& log);
  const std::string& options() const { return options_; }
  const std::string& log() const { return log_; }

 private:
  std::string options_;
  std::string log_;
};

// "CL_OUT_OF_RESOURCES" for -5, "CL_UNKNOWN_ERROR(-1234)" for codes it does not know.
std::string cl_error_name(int code);

// Throws ClError when code is not CL_SUCCESS.
void check_cl(int code, const char* call, const std::string& context = {});

}  // namespace bhcl
