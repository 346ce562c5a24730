#include "solvers/blas_threads.hpp"

#include <dlfcn.h>

#include "common/types.hpp"

namespace matlearn::solvers {

namespace {

// OpenBLAS's own controls, looked up at run time in the already loaded library (CHOLMOD links
// it; nothing is loaded here), so a build against another BLAS still links and runs.
void* openblas_symbol(const char* name) {
  for (const char* lib : {"libopenblas.so.0", "libopenblas.so", "libblas.so.3"}) {
    if (void* h = dlopen(lib, RTLD_LAZY | RTLD_NOLOAD)) {
      void* f = dlsym(h, name);
      dlclose(h);  // (RTLD_NOLOAD: only the reference just taken is dropped)
      if (f) return f;
    }
  }
  return dlsym(RTLD_DEFAULT, name);
}

}  // namespace

int blas_threads() {
  auto get = reinterpret_cast<int (*)()>(openblas_symbol("openblas_get_num_threads"));
  return get ? get() : -1;
}

bool set_blas_threads(int n) {
  if (n < 1) throw InvalidInput("set_blas_threads: n must be >= 1");
  auto set = reinterpret_cast<void (*)(int)>(openblas_symbol("openblas_set_num_threads"));
  if (!set) return false;
  set(n);
  return true;
}

}  // namespace matlearn::solvers
