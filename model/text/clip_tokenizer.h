// CLIP's byte-level BPE tokenizer as Stable Diffusion 1.5 uses it
// (transformers CLIPTokenizer with ftfy == OpenAI CLIP simple_tokenizer.py),
// built from an SD1.5 `tokenizer/` folder: vocab.json + merges.txt, plus the
// optional special_tokens_map.json / tokenizer_config.json for the padding
// token and model_max_length.
//
// Encode: text clean-up and pre-tokenization (model/text/clip_text_normalizer.h),
// then per word: UTF-8 bytes -> byte symbols (bytes_to_unicode), "</w>"
// appended to the last symbol, BPE merges by rank, vocabulary lookup;
// "<|startoftext|>" / "<|endoftext|>" map to their ids directly. The SD1.5
// pipeline call `tokenizer(prompt, padding="max_length", max_length=77,
// truncation=True)` keeps the first 75 content ids, wraps them in bos/eos and
// pads with the pad id (SD1.5: <|endoftext|> = 49407).
#ifndef FD_MODEL_TEXT_CLIP_TOKENIZER_H_
#define FD_MODEL_TEXT_CLIP_TOKENIZER_H_

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "model/checkpoint/file_source.h"

namespace fd::model {

// Ownership: owns its tables (~5 MB for the SD1.5 vocabulary); copies share
// them. Thread-safety: immutable after loading; all methods may be called
// concurrently.
class ClipTokenizer {
 public:
  struct Encoding {
    std::vector<int64_t> input_ids;       // max_length ids
    std::vector<int64_t> attention_mask;  // 1 for bos..eos, 0 for padding
  };

  // Loads <dir>/vocab.json and <dir>/merges.txt, and, when present,
  // special_tokens_map.json (pad_token) and tokenizer_config.json
  // (model_max_length). Errors: NOT_FOUND (missing vocab/merges),
  // INVALID_ARGUMENT (malformed file, naming it and the problem: bad json,
  // a merge line without two parts, special tokens missing from the vocab).
  static absl::StatusOr<ClipTokenizer> FromDirectory(const std::string& tokenizer_dir,
                                                     const FileSource& files = DiskFiles());
  // As above from explicit files; pad token <|endoftext|>, max length 77.
  static absl::StatusOr<ClipTokenizer> FromFiles(const std::string& vocab_json,
                                                 const std::string& merges_txt);

  int64_t bos_id() const;
  int64_t eos_id() const;
  int64_t pad_id() const;
  int model_max_length() const;
  int64_t vocab_size() const;

  // whitespace_clean(basic_clean(text)).lower(): the text BPE sees.
  std::string NormalizeText(std::string_view text) const;
  // The vocabulary strings of Encode(text) without bos/eos (byte-symbol
  // form, e.g. "photo</w>").
  std::vector<std::string> Tokenize(std::string_view text) const;
  // [bos] + ids + [eos], not truncated (= tokenizer(text).input_ids).
  std::vector<int64_t> Encode(std::string_view text) const;
  // Truncated to max_length (bos + first max_length - 2 ids + eos) and padded
  // with pad_id(). max_length <= 0 means model_max_length().
  Encoding EncodePadded(std::string_view text, int max_length = 0) const;
  // EncodePadded for each prompt: int64 [N, max_length] (CPU).
  // Errors: INTERNAL (LibTorch failure).
  absl::StatusOr<torch::Tensor> EncodeBatch(const std::vector<std::string>& prompts,
                                            int max_length = 0) const;

 private:
  struct Tables;
  explicit ClipTokenizer(std::shared_ptr<const Tables> tables) : tables_(std::move(tables)) {}
  static absl::StatusOr<ClipTokenizer> Load(const std::string& vocab_json,
                                            const std::string& merges_txt,
                                            const std::string& pad_token, int model_max_length,
                                            const FileSource& files);
  std::vector<std::string> Bpe(const std::string& word) const;

  std::shared_ptr<const Tables> tables_;
};

}  // namespace fd::model

#endif  // FD_MODEL_TEXT_CLIP_TOKENIZER_H_
