// Helpers shared by the scene generator tests.
#ifndef FD_TESTS_SCENEGEN_SCENEGEN_TEST_UTIL_H_
#define FD_TESTS_SCENEGEN_SCENEGEN_TEST_UTIL_H_

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <string>
#include <vector>

#include "tools/scenegen/encoding.h"
#include "tools/scenegen/sequence.h"

namespace fd::scenegen::testing {

// A fresh, empty folder under the gtest temp dir, removed again when the
// test program ends (scenegen_test_util.cc).
std::string FreshDir(const std::string& name);

inline std::string ReadBytes(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(file), std::istreambuf_iterator<char>());
}

// FNV-1a 64-bit hash of a byte string.
inline uint64_t Fnv1a(const std::string& bytes) {
  uint64_t h = 0xcbf29ce484222325ull;
  for (const unsigned char c : bytes) {
    h ^= c;
    h *= 0x100000001b3ull;
  }
  return h;
}

// Relative path -> hash of every regular file under dir.
inline std::map<std::string, uint64_t> HashTree(const std::string& dir) {
  std::map<std::string, uint64_t> hashes;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir)) {
    if (!entry.is_regular_file()) continue;
    hashes[std::filesystem::relative(entry.path(), dir).string()] =
        Fnv1a(ReadBytes(entry.path().string()));
  }
  return hashes;
}

inline Image8 ReadPngOrDie(const std::string& path) {
  absl::StatusOr<Image8> image = ReadPng(path);
  EXPECT_TRUE(image.ok()) << image.status();
  return image.ok() ? *image : Image8();
}

inline GenerationStats GenerateOrDie(const GeneratorOptions& options) {
  absl::StatusOr<GenerationStats> stats = GenerateSequence(options);
  EXPECT_TRUE(stats.ok()) << stats.status();
  return stats.ok() ? *stats : GenerationStats();
}

// The reference's luma weights (compute_irradiance_map), on 8-bit values.
inline float Luma(const Image8& rgb, int x, int y) {
  return 0.299f * rgb.at(x, y, 0) + 0.587f * rgb.at(x, y, 1) + 0.114f * rgb.at(x, y, 2);
}

// Mean absolute difference over all samples, in 8-bit units.
inline double MeanAbsDiff(const Image8& a, const Image8& b) {
  EXPECT_EQ(a.pixels.size(), b.pixels.size());
  double sum = 0.0;
  for (size_t i = 0; i < a.pixels.size() && i < b.pixels.size(); ++i) {
    sum += std::abs(int{a.pixels[i]} - int{b.pixels[i]});
  }
  return a.pixels.empty() ? 0.0 : sum / static_cast<double>(a.pixels.size());
}

// The reference's sky test (gbuffer_masking_utils.fill_black_pixels_in_basecolor):
// all BaseColor channels < 10 and Depth < 10.
inline bool SkyTest(const Image8& base_color, const Image8& depth, int x, int y) {
  return base_color.at(x, y, 0) < 10 && base_color.at(x, y, 1) < 10 &&
         base_color.at(x, y, 2) < 10 && depth.at(x, y, 0) < 10;
}

}  // namespace fd::scenegen::testing

#endif  // FD_TESTS_SCENEGEN_SCENEGEN_TEST_UTIL_H_
