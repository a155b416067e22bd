#include "lattice/fusion/profile.h"

#include <cmath>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"

namespace vasl::fusion {
namespace {

std::string Num(double v) { return absl::StrFormat("%.17g", v); }

}  // namespace

std::string ProfileToText(const WeightingProfile& p) {
  std::string s;
  absl::StrAppend(&s, "name ", p.name, "\n", "revision ", p.version, "\n");
  absl::StrAppend(&s, "alpha ", Num(p.alpha), "\nbeta ", Num(p.beta), "\nrho ", Num(p.rho), "\n");
  absl::StrAppend(&s, "kappa");
  for (double k : p.kappa) absl::StrAppend(&s, " ", Num(k));
  absl::StrAppend(&s, "\nv_min ", Num(p.v_min), "\nlambda_src ", Num(p.lambda_src),
                  "\ntheta_max_rad ", Num(p.theta_max_rad), "\nproximity_m ", Num(p.proximity_m),
                  "\nmode ", p.mode == FusionMode::kNearest ? "nearest" : "blend", "\n");
  for (const auto& [source, g] : p.scan_gain) absl::StrAppend(&s, "scan_gain ", source, " ", Num(g), "\n");
  for (const auto& [source, a] : p.channel_gain) {
    absl::StrAppend(&s, "channel_gain ", source);
    for (double g : a) absl::StrAppend(&s, " ", Num(g));
    absl::StrAppend(&s, "\n");
  }
  if (!p.lens_maps.empty()) {
    absl::StrAppend(&s, "lens_maps");
    for (int64_t id : p.lens_maps) absl::StrAppend(&s, " ", id);
    absl::StrAppend(&s, "\n");
  }
  return s;
}

absl::StatusOr<WeightingProfile> ProfileFromText(const std::string& text) {
  WeightingProfile p;
  int line_no = 0;
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    ++line_no;
    line = absl::StripAsciiWhitespace(line);
    if (line.empty()) continue;
    std::vector<absl::string_view> f = absl::StrSplit(line, ' ', absl::SkipEmpty());
    auto bad = [&](absl::string_view why) {
      return absl::DataLossError(absl::StrCat("stored profile, line ", line_no, " '", line, "': ", why));
    };
    std::vector<double> v;
    for (size_t i = 1; i < f.size(); ++i) {
      double x = 0.0;
      if (!absl::SimpleAtod(f[i], &x)) v.push_back(std::nan(""));
      else v.push_back(x);
    }
    const absl::string_view key = f[0];
    auto need = [&](size_t n) { return v.size() == n; };
    if (key == "name" && f.size() == 2) {
      p.name = std::string(f[1]);
    } else if (key == "mode" && f.size() == 2) {
      if (f[1] != "blend" && f[1] != "nearest") return bad("mode must be blend or nearest");
      p.mode = f[1] == "nearest" ? FusionMode::kNearest : FusionMode::kBlend;
    } else if (key == "revision" && need(1)) {
      p.version = int32_t(v[0]);
    } else if (key == "alpha" && need(1)) {
      p.alpha = v[0];
    } else if (key == "beta" && need(1)) {
      p.beta = v[0];
    } else if (key == "rho" && need(1)) {
      p.rho = v[0];
    } else if (key == "kappa" && (need(p.kappa.size()) || need(kOlderKappaCount))) {
      for (size_t i = 0; i < v.size(); ++i) p.kappa[i] = v[i];
    } else if (key == "v_min" && need(1)) {
      p.v_min = v[0];
    } else if (key == "lambda_src" && need(1)) {
      p.lambda_src = v[0];
    } else if (key == "theta_max_rad" && need(1)) {
      p.theta_max_rad = v[0];
    } else if (key == "proximity_m" && need(1)) {
      p.proximity_m = v[0];
    } else if (key == "scan_gain" && need(2)) {
      p.scan_gain[int32_t(v[0])] = v[1];
    } else if (key == "channel_gain" && need(1 + records::kValueChannels)) {
      std::array<double, records::kValueChannels> a{};
      for (int c = 0; c < records::kValueChannels; ++c) a[c] = v[1 + c];
      p.channel_gain[int32_t(v[0])] = a;
    } else if (key == "lens_maps" && !v.empty()) {
      for (double id : v) p.lens_maps.push_back(int64_t(id));
    } else {
      return bad("unknown key or wrong number of values");
    }
  }
  if (absl::Status s = ValidateProfile(p); !s.ok()) return absl::DataLossError(s.message());
  return p;
}

}  // namespace vasl::fusion
