// Fuzz target: arbitrary bytes (UTF-8 or not) as a prompt -> the CLIP BPE
// tokenizer with the real SD1.5 vocabulary (ftfy-style cleaning, lower
// casing, the word regex, byte-level BPE).
//
// The vocabulary is read once from $FD_CLIP_TOKENIZER_DIR, else from the
// golden set's clip/tokenizer/ (FD_DEFAULT_TOKENIZER_DIR, set by CMake).
// Properties: Encode() is [bos] ids [eos] with every id in the vocabulary;
// EncodePadded() has exactly max_length ids, bos first, an eos, a mask of
// ones then zeros; Tokenize() gives one string per id of Encode().
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <string_view>

#include "model/text/clip_tokenizer.h"
#include "tests/fuzz/fuzz_check.h"

namespace {

const fd::model::ClipTokenizer* tokenizer = nullptr;

}  // namespace

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  const char* dir = std::getenv("FD_CLIP_TOKENIZER_DIR");
  const std::string tokenizer_dir = dir != nullptr ? dir : FD_DEFAULT_TOKENIZER_DIR;
  absl::StatusOr<fd::model::ClipTokenizer> loaded =
      fd::model::ClipTokenizer::FromDirectory(tokenizer_dir);
  if (!loaded.ok()) {
    std::fprintf(stderr, "fuzz_clip_tokenizer: %s (set FD_CLIP_TOKENIZER_DIR)\n",
                 loaded.status().ToString().c_str());
    std::exit(2);
  }
  tokenizer = new fd::model::ClipTokenizer(*std::move(loaded));
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const std::vector<int64_t> ids = tokenizer->Encode(text);
  FD_FUZZ_CHECK(ids.size() >= 2, "bos and eos");
  FD_FUZZ_CHECK(ids.front() == tokenizer->bos_id() && ids.back() == tokenizer->eos_id(),
                "bos first, eos last");
  for (int64_t id : ids) FD_FUZZ_CHECK(id >= 0 && id < tokenizer->vocab_size(), "id in vocab");
  FD_FUZZ_CHECK(tokenizer->Tokenize(text).size() == ids.size() - 2, "one token per id");

  const fd::model::ClipTokenizer::Encoding padded = tokenizer->EncodePadded(text);
  const size_t length = static_cast<size_t>(tokenizer->model_max_length());
  FD_FUZZ_CHECK(padded.input_ids.size() == length && padded.attention_mask.size() == length,
                "max_length ids");
  FD_FUZZ_CHECK(padded.input_ids.front() == tokenizer->bos_id(), "bos");
  size_t ones = 0;
  while (ones < length && padded.attention_mask[ones] == 1) ++ones;
  for (size_t i = ones; i < length; ++i) FD_FUZZ_CHECK(padded.attention_mask[i] == 0, "mask");
  FD_FUZZ_CHECK(ones >= 2 && padded.input_ids[ones - 1] == tokenizer->eos_id(),
                "eos ends the text");
  return 0;
}
