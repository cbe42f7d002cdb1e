// Small synthetic G-buffer sequences in the authors' dataset layout for the
// trainer tests, and a TrainerOptions preset that trains in seconds.
#ifndef FD_TESTS_TRAINER_TRAINER_TEST_UTIL_H_
#define FD_TESTS_TRAINER_TRAINER_TEST_UTIL_H_

#include <cstdint>
#include <string>

#include "trainer/trainer_options.h"

namespace fd::trainer::testing {

struct SequenceSpec {
  int frames = 6;
  int width = 32;
  int height = 32;
  uint64_t seed = 0;
  bool metallic = true;
  bool sky = true;  // a black-basecolor, zero-depth band at the top (sky pixels)
};

// Writes DIR/{FinalImage,BaseColor,Normals,Depth,Roughness,Metallic}/
// <Buffer>_<nnnn>.png: a lit, textured scene that pans a few pixels per frame.
void WriteSequence(const std::string& dir, const SequenceSpec& spec);

// A fresh temporary folder (removed by the caller's TearDown or left in /tmp).
std::string MakeTempDir(const std::string& name);

// Options for a quick run on `data` (tiny preset, 32x32, few steps, one
// thread, no progress bar).
TrainerOptions QuickOptions(const std::string& data, const std::string& out);

}  // namespace fd::trainer::testing

#endif  // FD_TESTS_TRAINER_TRAINER_TEST_UTIL_H_
