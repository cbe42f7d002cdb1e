#include "model/runtime/core_budget.h"

#include <sched.h>

#include <algorithm>
#include <thread>
#include <utility>

namespace fd::model {
namespace {

int AvailableCores() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) == 0) return std::max(1, CPU_COUNT(&set));
  return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
}

}  // namespace

CoreBudget& CoreBudget::Process() {
  static CoreBudget* budget = new CoreBudget(AvailableCores());
  return *budget;
}

CoreBudget::CoreBudget(int cores) : cores_(std::max(1, cores)) {}

CoreBudget::Claim::Claim(Claim&& other) noexcept
    : budget_(other.budget_), cores_(std::exchange(other.cores_, 0)) {}

CoreBudget::Claim& CoreBudget::Claim::operator=(Claim&& other) noexcept {
  if (this != &other) {
    Release();
    budget_ = other.budget_;
    cores_ = std::exchange(other.cores_, 0);
  }
  return *this;
}

CoreBudget::Claim::~Claim() { Release(); }

void CoreBudget::Claim::Release() {
  if (cores_ > 0) budget_->in_use_.fetch_sub(cores_, std::memory_order_relaxed);
  cores_ = 0;
}

CoreBudget::Claim CoreBudget::Take(int cores) {
  cores = std::max(0, cores);
  in_use_.fetch_add(cores, std::memory_order_relaxed);
  return Claim(this, cores);
}

std::optional<CoreBudget::Claim> CoreBudget::TryTake(int cores) {
  cores = std::max(0, cores);
  int used = in_use_.load(std::memory_order_relaxed);
  while (used + cores <= cores_) {
    if (in_use_.compare_exchange_weak(used, used + cores, std::memory_order_relaxed)) {
      return Claim(this, cores);
    }
  }
  return std::nullopt;
}

}  // namespace fd::model
