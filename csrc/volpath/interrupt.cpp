#include "volpath/interrupt.h"

#include <c10/util/Exception.h>

#include <mutex>

#ifndef _WIN32
#include <signal.h>
#endif

namespace ta {
namespace volpath {

std::atomic<bool> g_interrupted{false};

#ifndef _WIN32
namespace {

std::mutex g_mutex;
int g_depth = 0;             // active scopes (guarded by g_mutex)
struct sigaction g_previous;  // the handler the outermost scope replaced

void on_sigint(int sig, siginfo_t* info, void* context) {
  g_interrupted.store(true, std::memory_order_relaxed);
  // pass it on: Python's handler marks the signal, so KeyboardInterrupt follows once the call returns
  if (g_previous.sa_flags & SA_SIGINFO) {
    if (g_previous.sa_sigaction != nullptr) g_previous.sa_sigaction(sig, info, context);
  } else if (g_previous.sa_handler != SIG_IGN && g_previous.sa_handler != SIG_DFL &&
             g_previous.sa_handler != nullptr) {
    g_previous.sa_handler(sig);
  }
  // SIG_DFL (no Python handler, e.g. an embedding host): the loops stop and the entry point throws
}

}  // namespace

InterruptScope::InterruptScope() {
  std::lock_guard<std::mutex> lock(g_mutex);
  if (g_depth++ == 0) {
    g_interrupted.store(false, std::memory_order_relaxed);
    struct sigaction action = {};
    action.sa_sigaction = on_sigint;
    action.sa_flags = SA_SIGINFO | SA_RESTART;
    sigemptyset(&action.sa_mask);
    sigaction(SIGINT, &action, &g_previous);
    if (!(g_previous.sa_flags & SA_SIGINFO) && g_previous.sa_handler == SIG_IGN) {
      sigaction(SIGINT, &g_previous, nullptr);  // SIGINT ignored by the host: leave it so
    }
  }
}

InterruptScope::~InterruptScope() {
  std::lock_guard<std::mutex> lock(g_mutex);
  if (--g_depth == 0) sigaction(SIGINT, &g_previous, nullptr);
}
#else
InterruptScope::InterruptScope() {}
InterruptScope::~InterruptScope() {}
#endif

void InterruptScope::throw_if_interrupted() const {
  TORCH_CHECK(!interrupted(), "interrupted (SIGINT): the render stopped early and returned nothing");
}

}  // namespace volpath
}  // namespace ta
