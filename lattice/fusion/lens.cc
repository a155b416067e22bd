#include "lattice/fusion/lens.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"

namespace vasl::fusion {

namespace {
constexpr int kC = records::kValueChannels;
}  // namespace

void LensMap::Sample(float u, float v, float* d, float* veil_out) const {
  const float x = std::clamp(u * float(grid_w) / float(image_w) - 0.5f, 0.0f, float(grid_w - 1));
  const float y = std::clamp(v * float(grid_h) / float(image_h) - 0.5f, 0.0f, float(grid_h - 1));
  const int x0 = std::min(int(x), grid_w - 1), y0 = std::min(int(y), grid_h - 1);
  const int x1 = std::min(x0 + 1, grid_w - 1), y1 = std::min(y0 + 1, grid_h - 1);
  const float fx = x - float(x0), fy = y - float(y0);
  const size_t c00 = (size_t(y0) * grid_w + x0) * kC, c10 = (size_t(y0) * grid_w + x1) * kC;
  const size_t c01 = (size_t(y1) * grid_w + x0) * kC, c11 = (size_t(y1) * grid_w + x1) * kC;
  const float w00 = (1 - fx) * (1 - fy), w10 = fx * (1 - fy), w01 = (1 - fx) * fy, w11 = fx * fy;
  for (int c = 0; c < kC; ++c) {
    d[c] = w00 * transmission[c00 + c] + w10 * transmission[c10 + c] +
           w01 * transmission[c01 + c] + w11 * transmission[c11 + c];
    veil_out[c] = w00 * veil[c00 + c] + w10 * veil[c10 + c] + w01 * veil[c01 + c] +
                  w11 * veil[c11 + c];
  }
}

double LensMap::DirtShare() const {
  size_t n = 0;
  for (size_t i = 0; i + kC <= transmission.size(); i += kC) {
    n += *std::min_element(&transmission[i], &transmission[i] + kC) < 1.0f;
  }
  return transmission.empty() ? 0.0 : double(n) / double(transmission.size() / kC);
}

double LensMap::VeilShare() const {
  size_t n = 0;
  for (size_t i = 0; i + kC <= veil.size(); i += kC) {
    n += *std::max_element(&veil[i], &veil[i] + kC) > 0.0f;
  }
  return veil.empty() ? 0.0 : double(n) / double(veil.size() / kC);
}

LensFactors AdjustForLens(const LensMap& map, const std::array<float, kC>& gain,
                          const float* uv, float* value) {
  float d[kC], v[kC];
  map.Sample(uv[0], uv[1], d, v);
  LensFactors out;
  for (int c = 0; c < kC; ++c) {
    const float veil = gain[c] * v[c];
    const float dc = std::max(d[c], 1e-3f);
    const float signal = value[c] > 0.0f ? std::max(0.0f, 1.0f - veil / value[c])
                                         : (veil > 0.0f ? 0.0f : 1.0f);
    out.dirt = std::min(out.dirt, std::min(dc, 1.0f));
    out.fog = std::min(out.fog, signal);
    value[c] = std::max(0.0f, (value[c] - veil) / dc);
  }
  out.dirt = std::clamp(out.dirt, 0.0f, 1.0f);
  out.fog = std::clamp(out.fog, 0.0f, 1.0f);
  return out;
}

std::shared_ptr<const LensTable> LensTable::Of(std::vector<std::shared_ptr<const LensMap>> maps) {
  auto table = std::make_shared<LensTable>();
  table->maps = std::move(maps);
  for (size_t i = 0; i < table->maps.size(); ++i) {
    for (const auto& [source, g] : table->maps[i]->source_gain) table->by_source[source] = i;
  }
  return table;
}

namespace {

std::string Num(float v) { return absl::StrFormat("%.9g", v); }

void AppendFloats(std::string& s, const char* key, const std::vector<float>& values) {
  absl::StrAppend(&s, key);
  for (float x : values) absl::StrAppend(&s, " ", Num(x));
  absl::StrAppend(&s, "\n");
}

}  // namespace

std::string LensMapToText(const LensMap& m) {
  std::string s;
  absl::StrAppend(&s, "rig ", m.rig, "\ncamera ", m.camera, "\nperiod ", m.period, "\n");
  absl::StrAppend(&s, "image ", m.image_w, " ", m.image_h, "\n");
  absl::StrAppend(&s, "grid ", m.grid_w, " ", m.grid_h, "\n");
  for (const auto& [source, g] : m.source_gain) {
    absl::StrAppend(&s, "source ", source, " ", Num(g[0]), " ", Num(g[1]), " ", Num(g[2]), "\n");
  }
  AppendFloats(s, "transmission", m.transmission);
  AppendFloats(s, "veil", m.veil);
  return s;
}

absl::StatusOr<LensMap> LensMapFromText(const std::string& text) {
  LensMap m;
  int line_no = 0;
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    ++line_no;
    if (absl::StripAsciiWhitespace(line).empty()) continue;
    const size_t space = line.find(' ');
    const absl::string_view key = line.substr(0, space);
    const absl::string_view rest =
        space == absl::string_view::npos ? absl::string_view() : line.substr(space + 1);
    auto bad = [&](absl::string_view why) {
      return absl::DataLossError(absl::StrCat("stored lens map, line ", line_no, " ('", key,
                                              "'): ", why));
    };
    if (key == "rig") { m.rig = std::string(rest); continue; }
    if (key == "camera") { m.camera = std::string(rest); continue; }
    if (key == "period") { m.period = std::string(rest); continue; }
    std::vector<float> v;
    for (absl::string_view f : absl::StrSplit(rest, ' ', absl::SkipEmpty())) {
      float x = 0.0f;
      if (!absl::SimpleAtof(f, &x) || !std::isfinite(x)) return bad("not a finite number");
      v.push_back(x);
    }
    if (key == "image" && v.size() == 2) {
      m.image_w = int(v[0]);
      m.image_h = int(v[1]);
    } else if (key == "grid" && v.size() == 2) {
      m.grid_w = int(v[0]);
      m.grid_h = int(v[1]);
    } else if (key == "source" && v.size() == 4) {
      m.source_gain[int32_t(v[0])] = {v[1], v[2], v[3]};
    } else if (key == "transmission") {
      m.transmission = std::move(v);
    } else if (key == "veil") {
      m.veil = std::move(v);
    } else {
      return bad("unknown key or wrong number of values");
    }
  }
  const size_t cells = size_t(std::max(0, m.grid_w)) * size_t(std::max(0, m.grid_h)) * kC;
  if (m.image_w <= 0 || m.image_h <= 0 || m.grid_w <= 0 || m.grid_h <= 0 ||
      m.transmission.size() != cells || m.veil.size() != cells) {
    return absl::DataLossError("stored lens map: its grid and its cells disagree");
  }
  for (float d : m.transmission) {
    if (!(d > 0.0f && d <= 1.0f)) return absl::DataLossError("stored lens map: D outside (0, 1]");
  }
  return m;
}

}  // namespace vasl::fusion
