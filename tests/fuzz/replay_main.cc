// Runs a libFuzzer harness over stored inputs without libFuzzer: the regular build (GCC, no
// sanitizers) compiles each harness of this folder with this driver, and ctest replays
// tests/fuzz/regressions/<harness> with it, so that ./deploy/test.sh keeps the harnesses
// compiling against the code they fuzz and runs every input that once broke one (the
// sanitizers' own checks stay deploy/fuzz.sh's).
//
//   fuzz_ingest_stream_replay DIR_OR_FILE...   (0 when every input ran; 1 when none was found)
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);
extern "C" int LLVMFuzzerInitialize(int* argc, char*** argv) __attribute__((weak));

// libFuzzer's byte mutator, which fuzz_ingest_stream's custom mutator calls: a replay never
// mutates, so reaching it is a bug of this driver.
extern "C" size_t LLVMFuzzerMutate(uint8_t*, size_t, size_t) {
  std::fprintf(stderr, "replay: LLVMFuzzerMutate called; a replay does not mutate\n");
  std::abort();
}

int main(int argc, char** argv) {
  if (LLVMFuzzerInitialize != nullptr) LLVMFuzzerInitialize(&argc, &argv);
  std::vector<std::filesystem::path> inputs;
  for (int i = 1; i < argc; ++i) {
    const std::filesystem::path arg(argv[i]);
    if (std::filesystem::is_directory(arg)) {
      for (const auto& entry : std::filesystem::directory_iterator(arg)) {
        if (entry.is_regular_file()) inputs.push_back(entry.path());
      }
    } else if (std::filesystem::is_regular_file(arg)) {
      inputs.push_back(arg);
    } else {
      std::fprintf(stderr, "replay: %s is neither a file nor a folder\n", argv[i]);
      return 1;
    }
  }
  std::sort(inputs.begin(), inputs.end());
  if (inputs.empty()) {
    std::fprintf(stderr, "replay: no input found\n");
    return 1;
  }
  for (const std::filesystem::path& path : inputs) {
    std::ifstream in(path, std::ios::binary);
    const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    if (!in.good() && !in.eof()) {
      std::fprintf(stderr, "replay: cannot read %s\n", path.c_str());
      return 1;
    }
    std::printf("replay: %s (%zu bytes)\n", path.filename().c_str(), bytes.size());
    std::fflush(stdout);
    LLVMFuzzerTestOneInput(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
  }
  std::printf("replay: %zu inputs ran\n", inputs.size());
  return 0;
}
