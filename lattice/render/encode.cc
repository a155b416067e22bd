/// @file encode.cc
/// @brief Row-streaming encoders of a RenderImage (VASL-MODEL §8 outputs): flat and deep EXR
///        (OpenEXR C++ API) and PNG (OpenImageIO), each writing through a ByteSink.
#include "lattice/render/encode.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <memory>
#include <stdexcept>
#include <thread>
#include <type_traits>
#include <utility>
#include <vector>

#if VASL_ISA_VARIANTS
#include <immintrin.h>
#endif

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfPartType.h>
#include <OpenEXR/ImfThreading.h>
#include <OpenEXR/ImfCompression.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIO.h>
#include <OpenEXR/ImfLineOrder.h>
#include <OpenEXR/ImfDeepFrameBuffer.h>
#include <OpenEXR/ImfDeepScanLineOutputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <Imath/half.h>
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <tbb/parallel_for.h>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "lattice/memory/isa.h"

namespace vasl::render {
namespace {

/// Bytes on their way to a ByteSink: contiguous writes are gathered into one run, sent when a
/// write lands elsewhere (a seek), when the run reaches kRunBytes, or on Flush. After the sink
/// fails, or after Close, writes are dropped.
class SinkBuffer {
 public:
  static constexpr size_t kRunBytes = size_t{1} << 20;

  explicit SinkBuffer(ByteSink sink) : sink_(std::move(sink)) {}

  /// Queues `n` bytes at `offset`; false when they were dropped.
  bool Write(int64_t offset, const char* data, size_t n) {
    if (closed_ || !status_.ok()) return false;
    if (!run_.empty() && offset != run_offset_ + int64_t(run_.size())) Flush();
    if (run_.empty()) run_offset_ = offset;
    run_.append(data, n);
    if (run_.size() >= kRunBytes) Flush();
    return status_.ok();
  }
  void Flush() {
    if (run_.empty() || closed_ || !status_.ok()) return;
    status_ = sink_(run_offset_, run_);
    run_.clear();
  }
  void Close() { closed_ = true; }
  bool closed() const { return closed_; }
  const absl::Status& status() const { return status_; }

 private:
  ByteSink sink_;
  std::string run_;
  int64_t run_offset_ = 0;
  absl::Status status_;
  bool closed_ = false;
};

/// An Imf::OStream writing into a SinkBuffer; it seeks freely (OpenEXR patches its offset
/// table last). A write the sink refuses throws, so that OpenEXR stops, unless the buffer was
/// closed or `quiet` is set (a destructor is writing).
class SinkOStream : public Imf::OStream {
 public:
  explicit SinkOStream(SinkBuffer* buffer) : Imf::OStream("render.exr"), buffer_(buffer) {}

  void write(const char c[], int n) override {
    const bool kept = buffer_->Write(int64_t(pos_), c, size_t(n));
    pos_ += uint64_t(n);
    if (!kept && !quiet_ && !buffer_->closed()) {
      throw std::runtime_error(std::string(buffer_->status().message()));
    }
  }
  uint64_t tellp() override { return pos_; }
  void seekp(uint64_t pos) override { pos_ = pos; }
  void set_quiet() { quiet_ = true; }

 private:
  SinkBuffer* buffer_;  ///< not owned
  uint64_t pos_ = 0;
  bool quiet_ = false;
};

/// An OIIO IOProxy writing into a SinkBuffer.
class SinkIOProxy : public OIIO::Filesystem::IOProxy {
 public:
  explicit SinkIOProxy(SinkBuffer* buffer) : IOProxy("", Write), buffer_(buffer) {}
  const char* proxytype() const override { return "vasl-sink"; }
  size_t write(const void* buf, size_t size) override {
    const size_t n = pwrite(buf, size, m_pos);
    m_pos += int64_t(n);
    return n;
  }
  size_t pwrite(const void* buf, size_t size, int64_t offset) override {
    // Refused only while the sink is open and failed; a closed encoder's last bytes go nowhere
    // quietly (libpng must not fail inside a destructor).
    if (!buffer_->Write(offset, static_cast<const char*>(buf), size) && !buffer_->closed()) {
      return 0;
    }
    end_ = std::max(end_, offset + int64_t(size));
    return size;
  }
  size_t size() const override { return size_t(end_); }

 private:
  SinkBuffer* buffer_;  ///< not owned
  int64_t end_ = 0;
};

absl::Status ValidateImage(const RenderImage& image) {
  if (image.width_px <= 0 || image.height_px <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("image size must be positive, got ",
                                                   image.width_px, "x", image.height_px));
  }
  const size_t pixels = static_cast<size_t>(image.width_px) * image.height_px;
  if (image.rgb.size() != 3 * pixels || image.depth_m.size() != pixels ||
      image.normal.size() != 3 * pixels || image.uncertainty.size() != pixels ||
      (!image.alpha.empty() && image.alpha.size() != pixels)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "image arrays disagree with its size ", image.width_px, "x", image.height_px, ": ",
        image.rgb.size(), " rgb, ", image.depth_m.size(), " depth, ", image.normal.size(),
        " normal, ", image.uncertainty.size(), " uncertainty values"));
  }
  return absl::OkStatus();
}

/// Coverage of pixel p (§8): images made before the alpha channel existed count every hit.
float Coverage(const RenderImage& image, size_t p) {
  if (image.alpha.size() == image.depth_m.size()) return image.alpha[p];
  return std::isfinite(image.depth_m[p]) ? 1.0f : 0.0f;
}

/// A frame-buffer base for a band that starts at row `row`: OpenEXR addresses pixel (x, y) at
/// base + x·xStride + y·yStride, so a band's own buffer is shifted back by `row` rows.
char* BandBase(const void* band, int row, size_t row_bytes) {
  return const_cast<char*>(static_cast<const char*>(band)) - ptrdiff_t(row) * ptrdiff_t(row_bytes);
}

/// `n` floats to halves (round to nearest even, as Imath::half): OpenEXR converts pixels only
/// as it reads them, so a writer of HALF channels hands it halves. With F16C (every CPU with
/// AVX2) eight at a time, the same bits (EncodeTest.HalfChannelsAreTheSameBitsOnEveryIsa).
void ToHalvesBaseline(const float* in, size_t n, Imath::half* out) {
  for (size_t i = 0; i < n; ++i) out[i] = Imath::half(in[i]);
}
#if VASL_ISA_VARIANTS
[[gnu::target("avx2,f16c")]] void ToHalvesF16c(const float* in, size_t n, Imath::half* out) {
  size_t i = 0;
  for (; i + 8 <= n; i += 8) {
    const __m128i h = _mm256_cvtps_ph(_mm256_loadu_ps(in + i), _MM_FROUND_TO_NEAREST_INT);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out + i), h);
  }
  ToHalvesBaseline(in + i, n - i, out + i);
}
#endif
void ToHalves(const float* in, size_t n, Imath::half* out) {
#if VASL_ISA_VARIANTS
  if (memory::WidestIsa() >= memory::Isa::kAvx2 && __builtin_cpu_supports("f16c")) {
    ToHalvesF16c(in, n, out);
    return;
  }
#endif
  ToHalvesBaseline(in, n, out);
}

/// Threads OpenEXR compresses a file's chunks on: one per core (its global pool, sized once).
int ExrThreads() {
  static const int threads = [] {
    const int n = std::max(1, int(std::thread::hardware_concurrency()));
    Imf::setGlobalThreadCount(n);
    return n;
  }();
  return threads;
}

/// What every format's encoder shares: the size, the rows written so far, the sink.
class EncoderBase : public RowEncoder {
 public:
  EncoderBase(int width_px, int height_px, ByteSink sink)
      : width_(width_px), height_(height_px), buffer_(std::move(sink)) {}
  int rows_sent() const override { return next_row_; }

 protected:
  absl::Status CheckRows(const RenderImage& image, int row_begin, int row_end) const {
    if (absl::Status s = ValidateImage(image); !s.ok()) return s;
    if (image.width_px != width_ || image.height_px != height_) {
      return absl::InvalidArgumentError(absl::StrCat("the image is ", image.width_px, "x",
                                                     image.height_px, ", the encoder's ",
                                                     width_, "x", height_));
    }
    if (row_begin != next_row_ || row_end <= row_begin || row_end > height_) {
      return absl::InvalidArgumentError(absl::StrCat("rows [", row_begin, ", ", row_end,
                                                     ") out of order: the next row is ",
                                                     next_row_, " of ", height_));
    }
    return buffer_.status();
  }
  absl::Status CheckComplete() const {
    if (next_row_ != height_) {
      return absl::FailedPreconditionError(absl::StrCat(
          "the encoder has ", next_row_, " of ", height_, " rows: it cannot finish"));
    }
    return buffer_.status();
  }
  /// The sink's failure, else the codec's.
  absl::Status Failed(const char* codec, const std::string& what) const {
    if (!buffer_.status().ok()) return buffer_.status();
    return absl::InternalError(absl::StrCat(codec, " failed to encode the render: ", what));
  }
  /// Sends the rows' bytes; the sink's status.
  absl::Status Sent(int row_end) {
    buffer_.Flush();
    next_row_ = row_end;
    return buffer_.status();
  }

  const int width_;
  const int height_;
  int next_row_ = 0;
  SinkBuffer buffer_;
};

/// zlib's level for the deep EXRs' ZIPS chunks (a reader needs no setting: the level is not
/// in the file). Level 1 rather than OpenEXR's default 4, since a user waits for the encoding:
/// a 4096×2048 render of the realistic corridor site took 2.3 s to encode instead of 3.3 s, its
/// file 74 MB instead of 68 MB (ZIP then; tests/bench/e2e_bench.py; 2026-11-27).
constexpr int kZipLevel = 1;

/// What the flat and the deep EXR encoders share: the stream into the sink, the OpenEXR file
/// (Imf::OutputFile or Imf::DeepScanLineOutputFile) whose header Open writes and whose offset
/// table Finish writes, and the write of one band's frame.
template <typename File>
class OpenExrEncoder : public EncoderBase {
 public:
  using EncoderBase::EncoderBase;
  ~OpenExrEncoder() override {
    buffer_.Close();  // an unfinished file's offset table goes nowhere
    file_.reset();
  }

  absl::Status Finish() override {
    if (absl::Status s = CheckComplete(); !s.ok()) return s;
    stream_.set_quiet();  // the destructor writes the offset table and must not throw
    file_.reset();
    buffer_.Flush();
    return buffer_.status();
  }

 protected:
  /// Writes the header: `channels` over the whole image, rows top to bottom, each FLOAT or,
  /// where `half` says so of its name, HALF.
  template <size_t N>
  absl::Status OpenFile(Imf::Compression compression, const char* const (&channels)[N],
                        bool (*half)(const char*) = nullptr) {
    try {
      Imf::Header header(width_, height_);  // data window (0,0)-(w-1,h-1)
      if constexpr (std::is_same_v<File, Imf::DeepScanLineOutputFile>) {
        header.setType(Imf::DEEPSCANLINE);
      }
      header.compression() = compression;
      header.zipCompressionLevel() = kZipLevel;
      header.lineOrder() = Imf::INCREASING_Y;  // row 0 = top
      for (const char* name : channels) {
        const bool as_half = half != nullptr && half(name);
        header.channels().insert(name, Imf::Channel(as_half ? Imf::HALF : Imf::FLOAT));
      }
      file_ = std::make_unique<File>(stream_, header, ExrThreads());
    } catch (const std::exception& e) {
      return Failed("OpenEXR", e.what());
    }
    return Sent(0);
  }
  /// Writes rows [row_begin, row_end) from `frame` (OpenEXR copies them: the band's buffers
  /// may change after) and sends their bytes.
  template <typename Frame>
  absl::Status WriteFrame(const Frame& frame, int row_begin, int row_end) {
    try {
      file_->setFrameBuffer(frame);
      file_->writePixels(row_end - row_begin);
    } catch (const std::exception& e) {
      return Failed("OpenEXR", e.what());
    }
    return Sent(row_end);
  }

 private:
  SinkOStream stream_{&buffer_};
  std::unique_ptr<File> file_;
};

/// EXR: channels R, G, B, N.x, N.y, N.z, U, A as HALF and Z as FLOAT; RLE, row 0 on top.
/// Half floats keep 11 significant bits (relative error at most 2^-11: a normal to about
/// 0.0005; largest finite value 65504; +inf kept): what a linear colour, a normal, a coverage or
/// an uncertainty needs, and what VFX tools read colour as; the depth keeps full float, so that
/// a point unprojected from it is as exact as the march. Against float channels with PIZ, as
/// before (decision, measured on 2 cores): BM_Encode/exr_4096 1.18 s and 105 MB → 0.43 s and
/// 68 MB; a 4096×2048 render end to end through vasld (tests/bench/e2e_bench.py) 2.65-2.74 →
/// 1.73-1.76 s. With half channels PIZ took 0.87-0.93 s for 54 MB and ZIP (level 1) 0.99 s for
/// 50 MB (end to end 2.34-2.38 s with PIZ): the smaller files cost the user more time than
/// their bytes save. RLE is lossless and every EXR reader decodes it.
/// Bands are gathered into runs of kRunRows rows per thread of OpenEXR's pool before OpenEXR
/// writes them, so that the pool compresses their chunks (a row each) in parallel; the file's
/// bytes are the same however the rows are split. Each band's values are converted as it
/// comes (ToHalves) and appended to the run.
class ExrEncoder final : public OpenExrEncoder<Imf::OutputFile> {
 public:
  using OpenExrEncoder::OpenExrEncoder;

  absl::Status Open() {
    return OpenFile(kCompression, kChannels,
                    [](const char* name) { return std::strcmp(name, "Z") != 0; });
  }
  int rows_sent() const override { return pending_row_; }

  absl::Status WriteRows(const RenderImage& image, int row_begin, int row_end) override {
    if (absl::Status s = CheckRows(image, row_begin, row_end); !s.ok()) return s;
    const size_t w = size_t(width_);
    const size_t first = size_t(row_begin) * w, pixels = size_t(row_end - row_begin) * w;
    const size_t at = depth_.size();  // pixels held before this band
    rgb_.resize(3 * (at + pixels));
    normal_.resize(3 * (at + pixels));
    uncertainty_.resize(at + pixels);
    alpha_.resize(at + pixels);
    ToHalves(image.rgb.data() + 3 * first, 3 * pixels, rgb_.data() + 3 * at);
    ToHalves(image.normal.data() + 3 * first, 3 * pixels, normal_.data() + 3 * at);
    ToHalves(image.uncertainty.data() + first, pixels, uncertainty_.data() + at);
    if (image.alpha.size() == image.depth_m.size()) {
      ToHalves(image.alpha.data() + first, pixels, alpha_.data() + at);
    } else {  // an image made before alpha existed
      for (size_t i = 0; i < pixels; ++i) alpha_[at + i] = Imath::half(Coverage(image, first + i));
    }
    depth_.insert(depth_.end(), image.depth_m.begin() + ptrdiff_t(first),
                  image.depth_m.begin() + ptrdiff_t(first + pixels));
    if (row_end - pending_row_ < RowsPerWrite() && row_end < height_) return Sent(row_end);

    // The run [pending_row_, row_end): per channel (kChannels' order) its first value in the
    // run's arrays and the values between pixels. OpenEXR's Slice takes a mutable pointer
    // (BandBase); writing only reads through it.
    struct Channel {
      const void* values;
      Imf::PixelType type;
      size_t x_bytes;
    };
    constexpr size_t kHalf = sizeof(Imath::half);
    const Channel channel[kChannelCount] = {
        {rgb_.data(), Imf::HALF, 3 * kHalf},        {rgb_.data() + 1, Imf::HALF, 3 * kHalf},
        {rgb_.data() + 2, Imf::HALF, 3 * kHalf},    {depth_.data(), Imf::FLOAT, sizeof(float)},
        {normal_.data(), Imf::HALF, 3 * kHalf},     {normal_.data() + 1, Imf::HALF, 3 * kHalf},
        {normal_.data() + 2, Imf::HALF, 3 * kHalf}, {uncertainty_.data(), Imf::HALF, kHalf},
        {alpha_.data(), Imf::HALF, kHalf}};
    Imf::FrameBuffer frame;
    for (size_t c = 0; c < kChannelCount; ++c) {
      const size_t row_bytes = channel[c].x_bytes * w;
      frame.insert(kChannels[c], Imf::Slice(channel[c].type,
                                            BandBase(channel[c].values, pending_row_, row_bytes),
                                            channel[c].x_bytes, row_bytes));
    }
    const absl::Status written = WriteFrame(frame, pending_row_, row_end);
    pending_row_ = row_end;
    rgb_.clear();
    normal_.clear();
    uncertainty_.clear();
    alpha_.clear();
    depth_.clear();
    return written;
  }

 private:
  static constexpr const char* kChannels[] = {"R", "G", "B", "Z", "N.x", "N.y", "N.z", "U", "A"};
  static constexpr size_t kChannelCount = std::size(kChannels);
  static constexpr Imf::Compression kCompression = Imf::RLE_COMPRESSION;
  static constexpr int kRunRows = 32;  ///< rows per thread of OpenEXR's pool in one write
  /// Rows OpenEXR is given at once, so that a streamed file grows every 64 rows on 2 cores.
  static int RowsPerWrite() { return kRunRows * ExrThreads(); }

  int pending_row_ = 0;  ///< the first row not yet written
  // The rows [pending_row_, next row) held for OpenEXR, as its channels store them.
  std::vector<Imath::half> rgb_, normal_, uncertainty_, alpha_;
  std::vector<float> depth_;
};

/// Deep EXR: per pixel its surface hits front to back as samples R, G, B, A, Z; ZIPS.
class DeepExrEncoder final : public OpenExrEncoder<Imf::DeepScanLineOutputFile> {
 public:
  using OpenExrEncoder::OpenExrEncoder;

  absl::Status Open() { return OpenFile(Imf::ZIPS_COMPRESSION, kChannels); }

  absl::Status WriteRows(const RenderImage& image, int row_begin, int row_end) override {
    if (absl::Status s = CheckRows(image, row_begin, row_end); !s.ok()) return s;
    const size_t w = size_t(width_);
    const size_t pixels = w * size_t(height_);
    const size_t L = size_t(std::max(1, image.layers));
    const bool deep = L > 1;
    if (deep && (image.layer_count.size() != pixels || image.deep_depth_m.size() != pixels * L ||
                 image.deep_rgb.size() != 3 * pixels * L ||
                 image.deep_alpha.size() != pixels * L)) {
      return absl::InvalidArgumentError(
          "the image's layer arrays disagree with its size and layers");
    }
    // The band's samples front to back, packed per pixel: R, G, B, A, Z each in its own array.
    const size_t first_pixel = size_t(row_begin) * w;
    const size_t n = size_t(row_end - row_begin) * w;
    count_.assign(n, 0);
    size_t total = 0;
    for (size_t i = 0; i < n; ++i) {
      const size_t p = first_pixel + i;
      count_[i] = deep ? image.layer_count[p] : (std::isfinite(image.depth_m[p]) ? 1u : 0u);
      total += count_[i];
    }
    for (std::vector<float>& v : values_) v.resize(total);
    for (std::vector<char*>& v : pointers_) v.resize(n);
    size_t o = 0;
    for (size_t i = 0; i < n; ++i) {
      const size_t p = first_pixel + i;
      for (size_t c = 0; c < std::size(kChannels); ++c) {
        pointers_[c][i] = reinterpret_cast<char*>(values_[c].data() + o);
      }
      for (size_t s = 0; s < count_[i]; ++s, ++o) {
        const size_t q = deep ? p * L + s : p;
        const float* rgb = deep ? &image.deep_rgb[3 * q] : &image.rgb[3 * p];
        for (int c = 0; c < 3; ++c) values_[c][o] = rgb[c];
        values_[3][o] = deep ? image.deep_alpha[q] : Coverage(image, p);
        values_[4][o] = deep ? image.deep_depth_m[q] : image.depth_m[p];
      }
    }
    Imf::DeepFrameBuffer frame;
    frame.insertSampleCountSlice(
        Imf::Slice(Imf::UINT, BandBase(count_.data(), row_begin, sizeof(unsigned int) * w),
                   sizeof(unsigned int), sizeof(unsigned int) * w));
    for (size_t c = 0; c < std::size(kChannels); ++c) {
      frame.insert(kChannels[c],
                   Imf::DeepSlice(Imf::FLOAT,
                                  BandBase(pointers_[c].data(), row_begin, sizeof(char*) * w),
                                  sizeof(char*), sizeof(char*) * w, sizeof(float)));
    }
    return WriteFrame(frame, row_begin, row_end);
  }

 private:
  static constexpr const char* kChannels[] = {"R", "G", "B", "A", "Z"};
  std::vector<unsigned int> count_;     ///< the band's samples per pixel
  std::vector<float> values_[5];        ///< the band's samples, per channel
  std::vector<char*> pointers_[5];      ///< per channel and pixel: its first sample
};

/// zlib's level for the PNG (OpenImageIO's default is 6): a 4096×2048 render of the corridor
/// site (BM_Encode/png_4096) 0.93 → 0.55 s to encode, its file 2.6 → 3.3 MB (levels 1 and 2
/// took the same time; level 3 0.62 s, 3.1 MB).
constexpr int kPngZlibLevel = 2;
/// libpng's row filter: "up" (each byte less the one above it) on every row, rather than its
/// adaptive choice among all five per row (decision, measured: BM_Encode/png_4096 0.42 s for
/// 3.30 MB adaptive, 0.28 s for 3.44 MB up, 0.27 s for 3.83 MB unfiltered, 0.29 s for 3.74 MB
/// sub, 0.32 s for 3.44 MB Paeth). The PNG is the render's last encoder to finish.
constexpr int kPngFilterUp = 0x20;  // PNG_FILTER_UP

/// PNG: RGBA 8-bit sRGB; alpha 0 where the ray hit nothing (black) or a vossel without colour
/// (neutral grey 128: a viewer shows it as transparent; one that ignores alpha, as grey).
class PngEncoder final : public EncoderBase {
 public:
  using EncoderBase::EncoderBase;
  ~PngEncoder() override {
    buffer_.Close();
    out_.reset();
  }

  absl::Status Open() {
    out_ = OIIO::ImageOutput::create("png");
    if (!out_) {
      return absl::InternalError(absl::StrCat("OpenImageIO has no PNG writer: ", OIIO::geterror()));
    }
    if (!out_->supports("ioproxy") || !out_->set_ioproxy(&proxy_)) {
      return absl::InternalError("OpenImageIO's PNG writer cannot write to a stream (no ioproxy)");
    }
    OIIO::ImageSpec spec(width_, height_, 4, OIIO::TypeDesc::UINT8);
    spec.alpha_channel = 3;
    spec.attribute("png:compressionLevel", kPngZlibLevel);
    spec.attribute("png:filter", kPngFilterUp);
    if (!out_->open("render.png", spec)) return Failed("OpenImageIO", out_->geterror());
    return Sent(0);
  }

  absl::Status WriteRows(const RenderImage& image, int row_begin, int row_end) override {
    if (absl::Status s = CheckRows(image, row_begin, row_end); !s.ok()) return s;
    const size_t first = size_t(row_begin) * size_t(width_);
    srgb_.resize(4 * size_t(row_end - row_begin) * size_t(width_));
    for (size_t i = 0; 4 * i < srgb_.size(); ++i) {
      const size_t p = first + i;
      const bool covered = Coverage(image, p) > 0.0f;
      const bool colourless = !covered && std::isfinite(image.depth_m[p]);
      for (int c = 0; c < 3; ++c) {
        srgb_[4 * i + c] = colourless ? uint8_t{128}
                           : !covered ? uint8_t{0}
                                      : geometry::LinearToSrgb8(image.rgb[3 * p + c]);
      }
      srgb_[4 * i + 3] = covered ? 255 : 0;
    }
    if (!out_->write_scanlines(row_begin, row_end, 0, OIIO::TypeDesc::UINT8, srgb_.data())) {
      return Failed("OpenImageIO", out_->geterror());
    }
    return Sent(row_end);
  }

  absl::Status Finish() override {
    if (absl::Status s = CheckComplete(); !s.ok()) return s;
    if (!out_->close()) return Failed("OpenImageIO", out_->geterror());
    buffer_.Flush();
    return buffer_.status();
  }

 private:
  SinkIOProxy proxy_{&buffer_};
  std::unique_ptr<OIIO::ImageOutput> out_;
  std::vector<uint8_t> srgb_;  ///< the band's pixels
};

template <typename Encoder>
absl::StatusOr<std::unique_ptr<RowEncoder>> Opened(int width_px, int height_px, ByteSink sink) {
  auto encoder = std::make_unique<Encoder>(width_px, height_px, std::move(sink));
  if (absl::Status s = encoder->Open(); !s.ok()) return s;
  return std::unique_ptr<RowEncoder>(std::move(encoder));
}

}  // namespace

absl::StatusOr<std::unique_ptr<RowEncoder>> RowEncoder::Create(ImageFormat format, int width_px,
                                                               int height_px, ByteSink sink) {
  if (width_px <= 0 || height_px <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("image size must be positive, got ", width_px, "x", height_px));
  }
  switch (format) {
    case ImageFormat::kExr:
      return Opened<ExrEncoder>(width_px, height_px, std::move(sink));
    case ImageFormat::kDeepExr:
      return Opened<DeepExrEncoder>(width_px, height_px, std::move(sink));
    case ImageFormat::kPng:
      return Opened<PngEncoder>(width_px, height_px, std::move(sink));
  }
  return absl::InvalidArgumentError("unknown image format");
}

absl::Status WriteRows(const std::vector<RowEncoder*>& encoders, const RenderImage& image,
                       int row_begin, int row_end) {
  std::vector<absl::Status> status(encoders.size());
  tbb::parallel_for(size_t{0}, encoders.size(), [&](size_t e) {
    status[e] = encoders[e]->WriteRows(image, row_begin, row_end);
  });
  for (absl::Status& s : status) {
    if (!s.ok()) return s;
  }
  return absl::OkStatus();
}

ByteSink AssembleInto(std::string* file) {
  return [file](int64_t offset, std::string_view run) {
    const size_t end = size_t(offset) + run.size();
    if (end > file->size()) file->resize(end);
    std::memcpy(file->data() + offset, run.data(), run.size());
    return absl::OkStatus();
  };
}

absl::StatusOr<std::string> Encode(ImageFormat format, const RenderImage& image) {
  std::string bytes;  // Create and WriteRows check the image
  auto encoder =
      RowEncoder::Create(format, image.width_px, image.height_px, AssembleInto(&bytes));
  if (!encoder.ok()) return encoder.status();
  if (absl::Status s = (*encoder)->WriteRows(image, 0, image.height_px); !s.ok()) return s;
  if (absl::Status s = (*encoder)->Finish(); !s.ok()) return s;
  return bytes;
}

absl::StatusOr<std::string> EncodeExr(const RenderImage& image) {
  return Encode(ImageFormat::kExr, image);
}

absl::StatusOr<std::string> EncodeDeepExr(const RenderImage& image) {
  return Encode(ImageFormat::kDeepExr, image);
}

absl::StatusOr<std::string> EncodePng(const RenderImage& image) {
  return Encode(ImageFormat::kPng, image);
}

}  // namespace vasl::render
