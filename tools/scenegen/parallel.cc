#include "tools/scenegen/parallel.h"

#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>

namespace fd::scenegen {

void ParallelFor(int count, int threads, const std::function<void(int)>& fn) {
  const int workers = std::max(1, std::min(threads, count));
  if (workers == 1) {
    for (int i = 0; i < count; ++i) fn(i);
    return;
  }
  std::atomic<int> next{0};
  auto work = [&]() {
    for (int i = next.fetch_add(1); i < count; i = next.fetch_add(1)) fn(i);
  };
  std::vector<std::thread> pool;
  pool.reserve(workers - 1);
  for (int t = 1; t < workers; ++t) pool.emplace_back(work);
  work();  // the calling thread works too
  for (std::thread& t : pool) t.join();
}

}  // namespace fd::scenegen
