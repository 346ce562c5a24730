#pragma once
/// A tiny self-contained test harness for ctest (no downloads): TEST_CASE registers a function,
/// CHECK* macros record failures with file:line and the values involved, main() runs them all
/// and returns non-zero if anything failed. One executable per test file.
#include <cmath>
#include <cstdio>
#include <exception>
#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace mltest {

struct Registry {
  std::vector<std::pair<std::string, std::function<void()>>> tests;
  int failures = 0;
  static Registry& get() {
    static Registry r;
    return r;
  }
};

struct Registrar {
  Registrar(const char* name, std::function<void()> fn) {
    Registry::get().tests.emplace_back(name, std::move(fn));
  }
};

inline void fail(const char* file, int line, const std::string& what) {
  ++Registry::get().failures;
  std::fprintf(stderr, "  FAILED %s:%d: %s\n", file, line, what.c_str());
}

/// |a - b| <= tol * max(1, |a|, |b|) (the per-entry relative tolerance of style.md).
inline bool close(double a, double b, double tol) {
  return std::isfinite(a) && std::isfinite(b) &&
         std::abs(a - b) <= tol * std::max({1.0, std::abs(a), std::abs(b)});
}

}  // namespace mltest

#define ML_CAT2(a, b) a##b
#define ML_CAT(a, b) ML_CAT2(a, b)
#define TEST_CASE(name)                                                      \
  static void name();                                                        \
  static mltest::Registrar ML_CAT(registrar_, name)(#name, name);            \
  static void name()

#define CHECK(cond)                                                          \
  do {                                                                       \
    if (!(cond)) mltest::fail(__FILE__, __LINE__, "CHECK(" #cond ")");       \
  } while (0)

#define CHECK_MSG(cond, msg)                                                 \
  do {                                                                       \
    if (!(cond)) mltest::fail(__FILE__, __LINE__, std::string(msg));         \
  } while (0)

/// Relative closeness with the values printed on failure; `ctx` says which entry/state.
#define CHECK_CLOSE(a, b, tol, ctx)                                                          \
  do {                                                                                       \
    const double ml_a = (a), ml_b = (b);                                                     \
    if (!mltest::close(ml_a, ml_b, (tol))) {                                                 \
      char ml_buf[512];                                                                      \
      std::snprintf(ml_buf, sizeof ml_buf, "%s: %s = %.12g vs %s = %.12g (tol %.1e)",         \
                    std::string(ctx).c_str(), #a, ml_a, #b, ml_b, double(tol));              \
      mltest::fail(__FILE__, __LINE__, ml_buf);                                              \
    }                                                                                        \
  } while (0)

#define CHECK_THROWS(expr, Type)                                                             \
  do {                                                                                       \
    bool ml_thrown = false;                                                                  \
    try {                                                                                    \
      expr;                                                                                  \
    } catch (const Type&) {                                                                  \
      ml_thrown = true;                                                                      \
    } catch (const std::exception& ml_e) {                                                   \
      mltest::fail(__FILE__, __LINE__,                                                       \
                   std::string(#expr " threw the wrong exception: ") + ml_e.what());         \
      ml_thrown = true;                                                                      \
    }                                                                                        \
    if (!ml_thrown) mltest::fail(__FILE__, __LINE__, #expr " did not throw " #Type);         \
  } while (0)

int main() {
  auto& reg = mltest::Registry::get();
  int failed_tests = 0;
  for (auto& [name, fn] : reg.tests) {
    const int before = reg.failures;
    std::printf("[ RUN  ] %s\n", name.c_str());
    try {
      fn();
    } catch (const std::exception& e) {
      mltest::fail(__FILE__, __LINE__, std::string("uncaught exception: ") + e.what());
    }
    const bool ok = reg.failures == before;
    failed_tests += !ok;
    std::printf("[ %s ] %s\n", ok ? " OK " : "FAIL", name.c_str());
  }
  std::printf("%zu tests, %d failed\n", reg.tests.size(), failed_tests);
  return failed_tests == 0 ? 0 : 1;
}
