// Ctrl-C during a render. The tracer runs for minutes with the GIL released, so Python's own SIGINT handling (a
// KeyboardInterrupt once the main thread runs bytecode again) would wait for the whole render. While an entry point
// runs, an InterruptScope installs a SIGINT handler that raises a flag and passes the signal on to the handler it
// replaced (Python's, which then raises KeyboardInterrupt when the call returns); the work loops poll the flag between
// sensor elements and stop, and the entry point throws "interrupted" instead of returning a partial image.
// No effect on what is computed when no signal comes (the random-number order is untouched).
#pragma once

#include <atomic>

namespace ta {
namespace volpath {

// Raised by the SIGINT handler of an active InterruptScope; read between sensor elements.
extern std::atomic<bool> g_interrupted;

inline bool interrupted() { return g_interrupted.load(std::memory_order_relaxed); }

// Installs the handler for its lifetime (nested and concurrent scopes share one installation; the outermost restores
// the handler it found). Without POSIX signals (Windows) it does nothing.
class InterruptScope {
 public:
  InterruptScope();
  ~InterruptScope();
  InterruptScope(const InterruptScope&) = delete;
  InterruptScope& operator=(const InterruptScope&) = delete;
  // Throws c10::Error "interrupted (SIGINT)" if the signal came while this scope was active.
  void throw_if_interrupted() const;
};

}  // namespace volpath
}  // namespace ta
