// Tests for model/text/clip_tokenizer.h and model/text/clip_text_normalizer.h against
// clip/tokenizer_golden.json: every string's normalized text, BPE tokens,
// unpadded ids and 77-padded ids/attention mask must match exactly.
#include "model/text/clip_tokenizer.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "model/text/clip_text_normalizer.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using ::testing::ElementsAreArray;
using ::testing::HasSubstr;

bool Exists(const std::string& path) { return std::ifstream(path).good(); }

// The SD1.5 vocabulary ships only with the dev golden set (clip/README.md):
// use the selected golden dir's copy if it has one, else the dev set's.
std::string TokenizerDir() {
  const std::string selected = fd::testing::GoldenPath("clip/tokenizer");
  if (Exists(selected + "/vocab.json")) return selected;
#ifdef FD_DEFAULT_GOLDEN_DIR
  return std::string(FD_DEFAULT_GOLDEN_DIR) + "/clip/tokenizer";
#else
  return selected;
#endif
}

const ClipTokenizer& Tokenizer() {
  static const ClipTokenizer* tokenizer = [] {
    auto t = ClipTokenizer::FromDirectory(TokenizerDir());
    EXPECT_TRUE(t.ok()) << t.status();
    return t.ok() ? new ClipTokenizer(*t) : nullptr;
  }();
  return *tokenizer;
}

nlohmann::json LoadGoldenJson() {
  std::ifstream in(fd::testing::GoldenPath("clip/tokenizer_golden.json"));
  EXPECT_TRUE(in.good()) << "missing clip/tokenizer_golden.json";
  std::stringstream buffer;
  buffer << in.rdbuf();
  return nlohmann::json::parse(buffer.str(), nullptr, /*allow_exceptions=*/false);
}

template <typename T>
std::vector<T> Vec(const nlohmann::json& j) {
  return j.get<std::vector<T>>();
}

TEST(ClipTokenizerTest, SpecialIdsMatchTheGoldenMeta) {
  const nlohmann::json golden = LoadGoldenJson();
  ASSERT_FALSE(golden.is_discarded());
  const nlohmann::json& meta = golden["meta"];
  EXPECT_EQ(Tokenizer().bos_id(), meta["bos"].get<int64_t>());
  EXPECT_EQ(Tokenizer().eos_id(), meta["eos"].get<int64_t>());
  EXPECT_EQ(Tokenizer().pad_id(), meta["pad"].get<int64_t>());
  EXPECT_EQ(Tokenizer().model_max_length(), meta["max_length"].get<int>());
  EXPECT_EQ(Tokenizer().vocab_size(), 49408);
}

TEST(ClipTokenizerTest, EveryGoldenStringMatchesExactly) {
  const nlohmann::json golden = LoadGoldenJson();
  ASSERT_FALSE(golden.is_discarded());
  const int max_length = golden["meta"]["max_length"].get<int>();
  int checked = 0;
  for (const nlohmann::json& entry : golden["entries"]) {
    const std::string text = entry["text"].get<std::string>();
    const std::string what = "entry " + std::to_string(entry["index"].get<int>()) + " " +
                             entry["tags"].dump() + ": " + nlohmann::json(text).dump();
    EXPECT_EQ(Tokenizer().NormalizeText(text), entry["normalized_text"].get<std::string>()) << what;
    // "tokens" are the vocabulary strings of ids_unpadded (bos and eos included).
    std::vector<std::string> tokens = {"<|startoftext|>"};
    for (std::string& t : Tokenizer().Tokenize(text)) tokens.push_back(std::move(t));
    tokens.push_back("<|endoftext|>");
    EXPECT_THAT(tokens, ElementsAreArray(Vec<std::string>(entry["tokens"]))) << what;
    EXPECT_THAT(Tokenizer().Encode(text), ElementsAreArray(Vec<int64_t>(entry["ids_unpadded"])))
        << what;
    const ClipTokenizer::Encoding padded = Tokenizer().EncodePadded(text, max_length);
    EXPECT_THAT(padded.input_ids, ElementsAreArray(Vec<int64_t>(entry["ids_77"]))) << what;
    EXPECT_THAT(padded.attention_mask, ElementsAreArray(Vec<int64_t>(entry["attention_mask_77"])))
        << what;
    ++checked;
  }
  EXPECT_GT(checked, 0);
  std::cout << "[golden] tokenizer strings checked: " << checked << "\n";
}

TEST(ClipTokenizerTest, EncodeBatchStacksPaddedIds) {
  auto batch = Tokenizer().EncodeBatch({"a photo of a cat", ""});
  ASSERT_TRUE(batch.ok()) << batch.status();
  ASSERT_EQ(batch->sizes(), (std::vector<int64_t>{2, 77}));
  EXPECT_EQ((*batch)[0][0].item<int64_t>(), 49406);
  EXPECT_EQ((*batch)[1][1].item<int64_t>(), 49407);  // "" -> bos, eos, pad...
  EXPECT_EQ((*batch)[1][76].item<int64_t>(), 49407);
}

// Pieces of the clean-up whose behaviour the golden strings cover only in
// part (checked against Python 3.11 / html.unescape / ftfy 6.3.1 results).
TEST(ClipTextNormalizerTest, PythonSemantics) {
  using clip_text::CleanText;
  using clip_text::DecodeUtf8;
  using clip_text::EncodeUtf8;
  // str.lower(): final sigma, dotted capital I.
  EXPECT_EQ(EncodeUtf8(clip_text::PythonLower(DecodeUtf8("ΟΔΟΣ ΣΑΣ"))), "οδος σας");
  EXPECT_EQ(EncodeUtf8(clip_text::PythonLower(DecodeUtf8("İ"))), "i\xCC\x87");
  // html.unescape: legacy names without ';', numeric references, C1 remap.
  EXPECT_EQ(EncodeUtf8(clip_text::HtmlUnescape(DecodeUtf8("&ampx &lt &#65;&#x42 &#128; &bogus;"))),
            "&x < AB \xE2\x82\xAC &bogus;");
  // ftfy: all-caps entities, ANSI escapes, decomposed Hangul, width.
  EXPECT_EQ(EncodeUtf8(clip_text::FtfyFixText(DecodeUtf8("P&EACUTE;REZ"))), "P\xC3\x89REZ");
  EXPECT_EQ(EncodeUtf8(clip_text::FtfyFixText(DecodeUtf8("\x1b[36mblue\x1b[0m"))), "blue");
  EXPECT_EQ(EncodeUtf8(clip_text::NormalizeNfc(DecodeUtf8("\xE1\x84\x92\xE1\x85\xA1\xE1\x86\xAB"))),
            "\xED\x95\x9C");  // HANGUL L + V + T -> U+D55C
  EXPECT_EQ(CleanText("  Ｈｅｌｌｏ\xE3\x80\x80ＷＯＲＬＤ  "), "hello world");
  // Invalid UTF-8 becomes U+FFFD instead of failing.
  EXPECT_EQ(CleanText("a\xFF"
                      "b"),
            "a\xEF\xBF\xBD"
            "b");
}

TEST(ClipTokenizerTest, MissingOrMalformedFilesAreReported) {
  auto missing = ClipTokenizer::FromDirectory("/nonexistent/tokenizer");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);

  const std::string dir = ::testing::TempDir();
  const std::string vocab = dir + "/h4_bad_vocab.json";
  const std::string merges = dir + "/h4_bad_merges.txt";
  std::ofstream(vocab) << "[1, 2, 3]";
  std::ofstream(merges) << "#version: 0.2\na b\n";
  auto bad_vocab = ClipTokenizer::FromFiles(vocab, merges);
  EXPECT_EQ(bad_vocab.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(bad_vocab.status().message(), HasSubstr("h4_bad_vocab.json"));

  std::ofstream(merges) << "#version: 0.2\nonlyonepart\n";
  auto bad_merges = ClipTokenizer::FromFiles(TokenizerDir() + "/vocab.json", merges);
  EXPECT_EQ(bad_merges.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(bad_merges.status().message(), HasSubstr(":2:"));
}

}  // namespace
}  // namespace fd::model
