// A main() for the fuzz targets when they are built without libFuzzer (the
// default preset, GCC): it runs every input of the given files and folders,
// then a bounded number of randomly mutated inputs derived from them. No
// coverage guidance: it keeps the targets compiling and alive in CI and
// replays crash files; the `fuzz` preset (clang, libFuzzer) does the real
// fuzzing.
//
// Accepts the libFuzzer command line the ctest wrapper passes:
//   <target> [-runs=N] [-seed=S] [-max_len=L] [-other=ignored ...] paths...
// -runs counts the mutated executions after the corpus (default 1000).
// Exit status: 0, or the target's crash (abort / sanitizer report).
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <random>
#include <string>
#include <string_view>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);
// Optional in a target, as in libFuzzer.
extern "C" __attribute__((weak)) int LLVMFuzzerInitialize(int* argc, char*** argv);

namespace {

namespace fs = std::filesystem;
using Bytes = std::vector<uint8_t>;

struct Options {
  uint64_t runs = 1000;
  uint64_t seed = 1;
  size_t max_len = 1 << 20;
  std::vector<std::string> paths;
};

bool ParseFlag(std::string_view arg, std::string_view name, uint64_t* value) {
  if (arg.substr(0, name.size()) != name) return false;
  *value = std::strtoull(std::string(arg.substr(name.size())).c_str(), nullptr, 10);
  return true;
}

Options ParseOptions(int argc, char** argv) {
  Options options;
  for (int i = 1; i < argc; ++i) {
    const std::string_view arg = argv[i];
    uint64_t value = 0;
    if (ParseFlag(arg, "-runs=", &value)) {
      options.runs = value;
    } else if (ParseFlag(arg, "-seed=", &value)) {
      options.seed = value;
    } else if (ParseFlag(arg, "-max_len=", &value)) {
      options.max_len = value;
    } else if (!arg.empty() && arg[0] == '-') {
      // Another libFuzzer flag (-artifact_prefix=, -max_total_time=, ...).
    } else {
      options.paths.emplace_back(arg);
    }
  }
  return options;
}

Bytes ReadFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return Bytes(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

std::vector<Bytes> LoadCorpus(const std::vector<std::string>& paths) {
  std::vector<fs::path> files;
  for (const std::string& path : paths) {
    std::error_code error;
    if (fs::is_directory(path, error)) {
      for (const fs::directory_entry& entry : fs::recursive_directory_iterator(path, error)) {
        if (entry.is_regular_file()) files.push_back(entry.path());
      }
    } else if (fs::is_regular_file(path, error)) {
      files.emplace_back(path);
    } else {
      std::fprintf(stderr, "standalone fuzz driver: no such file or folder: %s\n", path.c_str());
      std::exit(2);
    }
  }
  // Sorted, so that a seed gives the same mutations on every machine.
  std::sort(files.begin(), files.end());
  std::vector<Bytes> corpus;
  corpus.reserve(files.size());
  for (const fs::path& file : files) corpus.push_back(ReadFile(file));
  return corpus;
}

// Values that often sit on a boundary of a size or count check.
constexpr uint64_t kInteresting[] = {
    0,      1,      2,      7,       8,          0x7f,       0x80,       0xff,        0x100,
    0x7fff, 0x8000, 0xffff, 0x10000, 0x7fffffff, 0x80000000, 0xffffffff, ~uint64_t{0}};

// One random edit of `bytes` (libFuzzer's simplest mutators, in spirit).
void Mutate(Bytes& bytes, const std::vector<Bytes>& corpus, size_t max_len, std::mt19937_64& rng) {
  auto below = [&](size_t n) { return n == 0 ? size_t{0} : static_cast<size_t>(rng() % n); };
  switch (rng() % 8) {
    case 0:  // flip a bit
      if (!bytes.empty()) bytes[below(bytes.size())] ^= uint8_t(1u << below(8));
      break;
    case 1:  // set a byte
      if (!bytes.empty()) bytes[below(bytes.size())] = uint8_t(rng());
      break;
    case 2:  // insert bytes
      if (bytes.size() < max_len) {
        const size_t at = below(bytes.size() + 1);
        bytes.insert(bytes.begin() + at, 1 + below(8), uint8_t(rng()));
      }
      break;
    case 3:  // erase a range
      if (!bytes.empty()) {
        const size_t at = below(bytes.size());
        const size_t n = 1 + below(std::min<size_t>(bytes.size() - at, 16));
        bytes.erase(bytes.begin() + at, bytes.begin() + at + n);
      }
      break;
    case 4:  // truncate
      bytes.resize(below(bytes.size() + 1));
      break;
    case 5: {  // overwrite 1, 2, 4 or 8 bytes with an interesting value
      const size_t width = size_t{1} << below(4);
      if (bytes.size() >= width) {
        const size_t at = below(bytes.size() - width + 1);
        const uint64_t value = kInteresting[below(std::size(kInteresting))];
        std::memcpy(bytes.data() + at, &value, width);  // little endian
      }
      break;
    }
    case 6:  // copy a range of the input over another place
      if (bytes.size() >= 2) {
        const size_t from = below(bytes.size());
        const size_t to = below(bytes.size());
        const size_t n = 1 + below(std::min(bytes.size() - from, bytes.size() - to));
        std::memmove(bytes.data() + to, bytes.data() + from, n);
      }
      break;
    default: {  // splice: our head, another input's tail
      const Bytes& other = corpus[below(corpus.size())];
      const size_t head = below(bytes.size() + 1);
      const size_t tail = below(other.size() + 1);
      bytes.resize(head);
      bytes.insert(bytes.end(), other.begin() + tail, other.end());
      break;
    }
  }
  if (bytes.size() > max_len) bytes.resize(max_len);
}

// A copy in a buffer of exactly its size, so that ASan sees reads past it.
void RunOne(const Bytes& bytes) {
  std::unique_ptr<uint8_t[]> copy(new uint8_t[bytes.size() + 1]);
  std::copy(bytes.begin(), bytes.end(), copy.get());
  LLVMFuzzerTestOneInput(bytes.empty() ? nullptr : copy.get(), bytes.size());
}

}  // namespace

int main(int argc, char** argv) {
  if (LLVMFuzzerInitialize != nullptr) LLVMFuzzerInitialize(&argc, &argv);
  const Options options = ParseOptions(argc, argv);
  std::vector<Bytes> corpus = LoadCorpus(options.paths);
  for (const Bytes& input : corpus) RunOne(input);
  if (corpus.empty()) corpus.emplace_back();

  std::mt19937_64 rng(options.seed);
  for (uint64_t run = 0; run < options.runs; ++run) {
    Bytes input = corpus[rng() % corpus.size()];
    const int edits = 1 + static_cast<int>(rng() % 4);
    for (int i = 0; i < edits; ++i) Mutate(input, corpus, options.max_len, rng);
    RunOne(input);
  }
  std::printf("standalone fuzz driver: %zu corpus inputs and %llu mutated inputs ran, seed %llu\n",
              corpus.size(), static_cast<unsigned long long>(options.runs),
              static_cast<unsigned long long>(options.seed));
  return 0;
}
