#include "tests/scenegen/scenegen_test_util.h"

#include <unistd.h>

#include <mutex>

namespace fd::scenegen::testing {
namespace {

std::mutex& DirsMutex() {
  static auto* mutex = new std::mutex();
  return *mutex;
}
std::vector<std::string>& CreatedDirs() {
  static auto* dirs = new std::vector<std::string>();
  return *dirs;
}

// Removes every FreshDir folder after the last test.
class RemoveFreshDirs : public ::testing::Environment {
 public:
  void TearDown() override {
    std::lock_guard<std::mutex> lock(DirsMutex());
    for (const std::string& dir : CreatedDirs()) {
      std::error_code ec;
      std::filesystem::remove_all(dir, ec);
    }
    CreatedDirs().clear();
  }
};
::testing::Environment* const kRemoveFreshDirs =
    ::testing::AddGlobalTestEnvironment(new RemoveFreshDirs());

}  // namespace

std::string FreshDir(const std::string& name) {
  const std::filesystem::path dir = std::filesystem::path(::testing::TempDir()) /
                                    ("fd_scenegen_" + name + "_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  std::lock_guard<std::mutex> lock(DirsMutex());
  CreatedDirs().push_back(dir.string());
  return dir.string();
}

}  // namespace fd::scenegen::testing
