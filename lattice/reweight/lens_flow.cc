#include "lattice/reweight/lens_flow.h"

#include <algorithm>
#include <set>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace vasl::reweight {

namespace {

/// A bound of the period: empty, or an ISO 8601 time that compares as text (YYYY-MM-DD...).
bool PlausibleTime(const std::string& t) {
  if (t.empty()) return true;
  if (t.size() < 10 || t[4] != '-' || t[7] != '-') return false;
  for (int i : {0, 1, 2, 3, 5, 6, 8, 9}) {
    if (t[size_t(i)] < '0' || t[size_t(i)] > '9') return false;
  }
  return true;
}

}  // namespace

absl::StatusOr<LensOutcome> EstimateLensProfile(store::ProjectStore& store,
                                                const store::Snapshot& snapshot,
                                                const fusion::WeightingProfile& base,
                                                const LensRequest& request) {
  if (request.rig.empty()) {
    return absl::InvalidArgumentError("a lens map is found per rig: name the rig");
  }
  if (!PlausibleTime(request.from_utc) || !PlausibleTime(request.to_utc)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the period's bounds must be ISO 8601 times (YYYY-MM-DD...); got '", request.from_utc,
        "' and '", request.to_utc, "'"));
  }
  const bool bounded = !request.from_utc.empty() || !request.to_utc.empty();
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(snapshot.version);
  if (!scans.ok()) return scans.status();
  std::vector<const store::ScanInfo*> in_period;
  std::string first, last;
  for (const store::ScanInfo& scan : *scans) {
    if (scan.rig != request.rig) continue;
    const std::string& t = scan.captured_utc;
    // A bound compares on its own length: "2026-11-24" as `to` takes the whole day.
    const bool before = !request.from_utc.empty() && t < request.from_utc;
    const bool after =
        !request.to_utc.empty() && t.substr(0, request.to_utc.size()) > request.to_utc;
    if (bounded && (t.empty() || before || after)) continue;
    in_period.push_back(&scan);
    if (!t.empty() && (first.empty() || t < first)) first = t;
    if (!t.empty() && t > last) last = t;
  }
  if (in_period.empty()) {
    return absl::NotFoundError(absl::StrCat("no scan of rig '", request.rig, "'",
                                            bounded ? " was captured in the period" : "",
                                            " in version ", snapshot.version));
  }
  std::set<std::string> cameras;
  for (const store::ScanInfo* scan : in_period) {
    for (const store::SourceInfo& src : scan->sources) {
      if (src.modality == records::Modality::kRgb) cameras.insert(src.name);
    }
  }
  std::string camera = request.camera;
  if (camera.empty()) {
    if (cameras.size() != 1) {
      return absl::InvalidArgumentError(absl::StrCat(
          "rig '", request.rig, "' has ", cameras.size(), " camera names (",
          absl::StrJoin(cameras, ", "), "): name the camera"));
    }
    camera = *cameras.begin();
  }
  LensOutcome out;
  for (const store::ScanInfo* scan : in_period) {
    for (const store::SourceInfo& src : scan->sources) {
      if (src.modality == records::Modality::kRgb && src.name == camera) {
        out.frames.push_back({src.id, src.width_px, src.height_px});
      }
    }
  }
  if (out.frames.empty()) {
    return absl::NotFoundError(absl::StrCat("rig '", request.rig, "' has no camera '", camera,
                                            "' in the period (its cameras: ",
                                            absl::StrJoin(cameras, ", "), ")"));
  }

  // The base without any map of this rig's camera: the new one takes its place. Its maps as
  // loaded (LoadProfile resolves them), or read now for a base that was not.
  fusion::WeightingProfile resolved = base;
  if (resolved.lens == nullptr) {
    if (absl::Status s = ResolveLensMaps(store, resolved); !s.ok()) return s;
  }
  fusion::WeightingProfile stripped = resolved;
  stripped.lens_maps.clear();
  std::vector<std::shared_ptr<const fusion::LensMap>> kept;
  if (resolved.lens != nullptr) {
    for (const std::shared_ptr<const fusion::LensMap>& m : resolved.lens->maps) {
      if (m->rig == request.rig && m->camera == camera) {
        out.replaced_map = m->id;
      } else {
        stripped.lens_maps.push_back(m->id);
        kept.push_back(m);
      }
    }
  }
  stripped.lens = kept.empty() ? nullptr : fusion::LensTable::Of(std::move(kept));
  absl::StatusOr<LensEstimate> estimate =
      EstimateLensMap(snapshot.records, snapshot.geometry.size(),
                      snapshot.geometry.vossel_size_m, stripped, out.frames, request.options);
  if (!estimate.ok()) return estimate.status();
  out.estimate = std::move(*estimate);
  fusion::LensMap& map = out.estimate.map;
  map.rig = request.rig;
  map.camera = camera;
  map.period = absl::StrCat(out.frames.size(), " frames",
                            first.empty() ? "" : absl::StrCat(", captured ", first, " to ", last));
  absl::StatusOr<store::StoredLensMap> stored =
      store.PutLensMap(map.rig, map.camera, fusion::LensMapToText(map));
  if (!stored.ok()) return stored.status();
  map.id = out.map_id = stored->id;
  map.created_utc = stored->created_utc;

  fusion::WeightingProfile next = stripped;
  next.name = !request.name.empty() ? request.name
              : base.name == fusion::kDefaultProfileName ? std::string("lens")
                                                         : base.name;
  next.lens_maps.push_back(out.map_id);
  absl::StatusOr<NamedProfile> made = CreateProfile(store, next);
  if (!made.ok()) return made.status();
  out.profile = std::move(*made);
  return out;
}

}  // namespace vasl::reweight
