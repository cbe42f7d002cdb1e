#include "model/text/clip_tokenizer.h"

#include <torch/torch.h>

#include <algorithm>
#include <climits>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <unordered_map>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"
#include "model/text/clip_text_normalizer.h"

namespace fd::model {
namespace {

using Json = nlohmann::json;

constexpr char kStartOfText[] = "<|startoftext|>";
constexpr char kEndOfText[] = "<|endoftext|>";
constexpr char kEndOfWord[] = "</w>";

// A tokenizer file through `files`, NOT_FOUND naming it when missing.
absl::StatusOr<std::string> ReadFile(const FileSource& files, const std::string& path) {
  absl::StatusOr<std::string> text = files.ReadText(path);
  if (text.status().code() == absl::StatusCode::kNotFound) {
    return absl::NotFoundError(absl::StrCat("tokenizer file not found: ", path));
  }
  return text;
}

// bytes_to_unicode(): printable Latin-1 bytes map to themselves, the other 68
// bytes to U+0100.. in byte order. Returns each byte's symbol as UTF-8.
std::vector<std::string> ByteSymbols() {
  std::vector<int> code(256, -1);
  for (int b = '!'; b <= '~'; ++b) code[b] = b;
  for (int b = 0xA1; b <= 0xAC; ++b) code[b] = b;
  for (int b = 0xAE; b <= 0xFF; ++b) code[b] = b;
  int n = 0;
  for (int b = 0; b < 256; ++b) {
    if (code[b] < 0) code[b] = 256 + n++;
  }
  std::vector<std::string> symbols(256);
  for (int b = 0; b < 256; ++b) {
    symbols[b] = clip_text::EncodeUtf8(std::u32string(1, static_cast<char32_t>(code[b])));
  }
  return symbols;
}

// A special token's string from special_tokens_map.json: "..." or
// {"content": "...", ...}.
std::string TokenContent(const Json& value) {
  if (value.is_string()) return value.get<std::string>();
  if (value.is_object() && value.contains("content") && value["content"].is_string()) {
    return value["content"].get<std::string>();
  }
  return "";
}

}  // namespace

struct ClipTokenizer::Tables {
  std::unordered_map<std::string, int64_t> vocab;
  std::unordered_map<std::string, int> merge_ranks;  // "left right" -> rank
  std::vector<std::string> byte_symbols;
  int64_t bos = 0;
  int64_t eos = 0;
  int64_t pad = 0;
  int model_max_length = 77;
};

absl::StatusOr<ClipTokenizer> ClipTokenizer::FromFiles(const std::string& vocab_json,
                                                       const std::string& merges_txt) {
  return Load(vocab_json, merges_txt, kEndOfText, 77, DiskFiles());
}

absl::StatusOr<ClipTokenizer> ClipTokenizer::FromDirectory(const std::string& dir,
                                                           const FileSource& files) {
  std::string pad_token = kEndOfText;
  int max_length = 77;
  const std::string special_path = dir + "/special_tokens_map.json";
  if (files.IsFile(special_path)) {
    FD_ASSIGN_OR_RETURN(const std::string text, ReadFile(files, special_path));
    const Json special = Json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (special.is_discarded() || !special.is_object()) {
      return absl::InvalidArgumentError(absl::StrCat(special_path, ": not a JSON object"));
    }
    if (special.contains("pad_token")) {
      pad_token = TokenContent(special["pad_token"]);
      if (pad_token.empty()) {
        return absl::InvalidArgumentError(absl::StrCat(special_path, ": pad_token has no content"));
      }
    }
  }
  const std::string config_path = dir + "/tokenizer_config.json";
  if (files.IsFile(config_path)) {
    FD_ASSIGN_OR_RETURN(const std::string text, ReadFile(files, config_path));
    const Json config = Json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (config.is_discarded() || !config.is_object()) {
      return absl::InvalidArgumentError(absl::StrCat(config_path, ": not a JSON object"));
    }
    // transformers writes a huge sentinel (1e30) when no limit is known.
    if (auto it = config.find("model_max_length"); it != config.end() && it->is_number()) {
      const double value = it->get<double>();
      if (value >= 2 && value <= 1e6) max_length = static_cast<int>(value);
    }
  }
  return Load(dir + "/vocab.json", dir + "/merges.txt", pad_token, max_length, files);
}

absl::StatusOr<ClipTokenizer> ClipTokenizer::Load(const std::string& vocab_json,
                                                  const std::string& merges_txt,
                                                  const std::string& pad_token,
                                                  int model_max_length, const FileSource& files) {
  auto tables = std::make_shared<Tables>();
  tables->model_max_length = model_max_length;
  tables->byte_symbols = ByteSymbols();

  FD_ASSIGN_OR_RETURN(const std::string vocab_text, ReadFile(files, vocab_json));
  const Json vocab = Json::parse(vocab_text, nullptr, /*allow_exceptions=*/false);
  if (vocab.is_discarded() || !vocab.is_object() || vocab.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(vocab_json, ": expected a JSON object {token: id}"));
  }
  for (auto it = vocab.begin(); it != vocab.end(); ++it) {
    if (!it.value().is_number_integer() || it.value().get<int64_t>() < 0 ||
        it.value().get<int64_t>() >= (int64_t{1} << 31)) {
      return absl::InvalidArgumentError(
          absl::StrCat(vocab_json, ": id of token '", it.key(), "' is not a valid integer"));
    }
    const int64_t id = it.value().get<int64_t>();
    tables->vocab.emplace(it.key(), id);
  }

  FD_ASSIGN_OR_RETURN(const std::string merges_text, ReadFile(files, merges_txt));
  std::istringstream lines(merges_text);
  std::string line;
  int line_number = 0;
  int rank = 0;
  // CLIPTokenizer: merges = file.strip().split("\n")[1 : 49152 - 256 - 2 + 1]
  constexpr int kMaxMerges = 49152 - 256 - 2;
  while (std::getline(lines, line) && rank < kMaxMerges) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line_number == 1 && line.rfind("#version", 0) == 0) continue;
    if (line.empty()) continue;
    const size_t space = line.find(' ');
    if (space == std::string::npos || space == 0 || space + 1 >= line.size() ||
        line.find(' ', space + 1) != std::string::npos) {
      return absl::InvalidArgumentError(absl::StrCat(
          merges_txt, ":", line_number, ": expected '<left> <right>', got '", line, "'"));
    }
    tables->merge_ranks.emplace(line, rank++);
  }
  if (tables->merge_ranks.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(merges_txt, ": no merges"));
  }

  for (const auto& [token, field] : {std::pair<std::string, int64_t*>{kStartOfText, &tables->bos},
                                     {kEndOfText, &tables->eos},
                                     {pad_token, &tables->pad}}) {
    auto it = tables->vocab.find(token);
    if (it == tables->vocab.end()) {
      return absl::InvalidArgumentError(
          absl::StrCat(vocab_json, ": special token '", token, "' is not in the vocabulary"));
    }
    *field = it->second;
  }
  for (const std::string& symbol : tables->byte_symbols) {
    if (!tables->vocab.count(symbol) || !tables->vocab.count(symbol + kEndOfWord)) {
      return absl::InvalidArgumentError(absl::StrCat(vocab_json, ": byte symbol '", symbol,
                                                     "' (or with </w>) is not in the vocabulary"));
    }
  }
  return ClipTokenizer(std::move(tables));
}

int64_t ClipTokenizer::bos_id() const { return tables_->bos; }
int64_t ClipTokenizer::eos_id() const { return tables_->eos; }
int64_t ClipTokenizer::pad_id() const { return tables_->pad; }
int ClipTokenizer::model_max_length() const { return tables_->model_max_length; }
int64_t ClipTokenizer::vocab_size() const { return static_cast<int64_t>(tables_->vocab.size()); }

std::string ClipTokenizer::NormalizeText(std::string_view text) const {
  return clip_text::CleanText(text);
}

// simple_tokenizer.SimpleTokenizer.bpe for one pre-tokenized word.
std::vector<std::string> ClipTokenizer::Bpe(const std::string& word) const {
  if (word == kStartOfText || word == kEndOfText) return {word};
  std::vector<std::string> symbols;
  for (unsigned char b : word) symbols.push_back(tables_->byte_symbols[b]);
  if (symbols.empty()) return symbols;
  symbols.back() += kEndOfWord;
  while (symbols.size() > 1) {
    int best_rank = INT_MAX;
    size_t best = 0;
    for (size_t i = 0; i + 1 < symbols.size(); ++i) {
      auto it = tables_->merge_ranks.find(symbols[i] + " " + symbols[i + 1]);
      if (it != tables_->merge_ranks.end() && it->second < best_rank) {
        best_rank = it->second;
        best = i;
      }
    }
    if (best_rank == INT_MAX) break;
    const std::string first = symbols[best];
    const std::string second = symbols[best + 1];
    std::vector<std::string> merged;
    for (size_t i = 0; i < symbols.size();) {
      if (i + 1 < symbols.size() && symbols[i] == first && symbols[i + 1] == second) {
        merged.push_back(first + second);
        i += 2;
      } else {
        merged.push_back(symbols[i]);
        ++i;
      }
    }
    symbols = std::move(merged);
  }
  return symbols;
}

std::vector<std::string> ClipTokenizer::Tokenize(std::string_view text) const {
  std::vector<std::string> tokens;
  for (const std::string& word : clip_text::PreTokenize(NormalizeText(text))) {
    for (std::string& token : Bpe(word)) tokens.push_back(std::move(token));
  }
  return tokens;
}

std::vector<int64_t> ClipTokenizer::Encode(std::string_view text) const {
  std::vector<int64_t> ids = {tables_->bos};
  for (const std::string& token : Tokenize(text)) {
    // Every byte symbol (with and without </w>) is in the vocabulary (checked
    // at load time) and merges only produce vocabulary entries, so the
    // lookup cannot miss for a consistent vocab/merges pair.
    auto it = tables_->vocab.find(token);
    ids.push_back(it != tables_->vocab.end() ? it->second : tables_->eos);
  }
  ids.push_back(tables_->eos);
  return ids;
}

ClipTokenizer::Encoding ClipTokenizer::EncodePadded(std::string_view text, int max_length) const {
  if (max_length <= 0) max_length = tables_->model_max_length;
  max_length = std::max(max_length, 2);
  std::vector<int64_t> ids = Encode(text);
  if (static_cast<int>(ids.size()) > max_length) {
    ids.resize(max_length - 1);
    ids.push_back(tables_->eos);
  }
  Encoding out;
  out.attention_mask.assign(ids.size(), 1);
  out.input_ids = std::move(ids);
  out.input_ids.resize(max_length, tables_->pad);
  out.attention_mask.resize(max_length, 0);
  return out;
}

absl::StatusOr<torch::Tensor> ClipTokenizer::EncodeBatch(const std::vector<std::string>& prompts,
                                                         int max_length) const {
  if (max_length <= 0) max_length = tables_->model_max_length;
  max_length = std::max(max_length, 2);
  std::vector<int64_t> flat;
  for (const std::string& prompt : prompts) {
    const Encoding e = EncodePadded(prompt, max_length);
    flat.insert(flat.end(), e.input_ids.begin(), e.input_ids.end());
  }
  return TorchCall("ClipTokenizer::EncodeBatch", [&]() -> absl::StatusOr<torch::Tensor> {
    return torch::tensor(flat, torch::kInt64)
        .view({static_cast<int64_t>(prompts.size()), max_length});
  });
}

}  // namespace fd::model
