#include "lattice/reweight/profiles.h"

#include "absl/strings/str_cat.h"
#include "lattice/fusion/fuse.h"

namespace vasl::reweight {

namespace {

absl::StatusOr<fusion::LensMap> FromStored(const store::StoredLensMap& stored) {
  absl::StatusOr<fusion::LensMap> map = fusion::LensMapFromText(stored.text);
  if (!map.ok()) return map.status();
  map->id = stored.id;
  map->created_utc = stored.created_utc;
  return map;
}

}  // namespace

absl::StatusOr<fusion::LensMap> LoadLensMap(const store::ProjectStore& store, int64_t id) {
  absl::StatusOr<store::StoredLensMap> stored = store.GetLensMap(id);
  if (!stored.ok()) return stored.status();
  return FromStored(*stored);
}

absl::StatusOr<std::vector<fusion::LensMap>> ListLensMaps(const store::ProjectStore& store) {
  absl::StatusOr<std::vector<store::StoredLensMap>> stored = store.ListLensMaps();
  if (!stored.ok()) return stored.status();
  std::vector<fusion::LensMap> out;
  for (const store::StoredLensMap& s : *stored) {
    absl::StatusOr<fusion::LensMap> map = FromStored(s);
    if (!map.ok()) return map.status();
    out.push_back(std::move(*map));
  }
  return out;
}

absl::Status ResolveLensMaps(const store::ProjectStore& store, fusion::WeightingProfile& profile) {
  if (profile.lens_maps.empty()) {
    profile.lens = nullptr;
    return absl::OkStatus();
  }
  std::vector<std::shared_ptr<const fusion::LensMap>> maps;
  for (int64_t id : profile.lens_maps) {
    absl::StatusOr<fusion::LensMap> map = LoadLensMap(store, id);
    if (!map.ok()) return map.status();
    maps.push_back(std::make_shared<const fusion::LensMap>(std::move(*map)));
  }
  profile.lens = fusion::LensTable::Of(std::move(maps));
  return absl::OkStatus();
}

absl::StatusOr<NamedProfile> LoadProfile(const store::ProjectStore& store, const std::string& name,
                                         int32_t revision) {
  if (name == fusion::kDefaultProfileName) {
    if (revision > 1) {
      return absl::NotFoundError(absl::StrCat("the built-in profile \"default\" has only revision 1"));
    }
    return NamedProfile{};
  }
  absl::StatusOr<store::StoredProfile> stored = store.GetProfile(name, revision);
  if (!stored.ok()) return stored.status();
  absl::StatusOr<fusion::WeightingProfile> p = fusion::ProfileFromText(stored->text);
  if (!p.ok()) return p.status();
  p->name = stored->name;
  p->version = stored->revision;
  if (absl::Status s = ResolveLensMaps(store, *p); !s.ok()) return s;
  return NamedProfile{std::move(*p), stored->created_utc};
}

absl::StatusOr<NamedProfile> CreateProfile(store::ProjectStore& store,
                                           fusion::WeightingProfile profile) {
  if (profile.name == fusion::kDefaultProfileName) {
    return absl::InvalidArgumentError(
        "\"default\" is the built-in profile of the model's defaults; give the profile "
        "another name");
  }
  if (absl::Status s = fusion::ValidateProfile(profile); !s.ok()) return s;
  if (absl::Status s = ResolveLensMaps(store, profile); !s.ok()) return s;
  absl::StatusOr<store::StoredProfile> stored =
      store.PutProfile(profile.name, [&profile](int32_t revision) {
        profile.version = revision;
        return fusion::ProfileToText(profile);
      });
  if (!stored.ok()) return stored.status();
  profile.version = stored->revision;
  return NamedProfile{std::move(profile), stored->created_utc};
}

absl::StatusOr<std::vector<NamedProfile>> ListProfiles(const store::ProjectStore& store) {
  absl::StatusOr<std::vector<store::StoredProfile>> stored = store.ListProfiles();
  if (!stored.ok()) return stored.status();
  std::vector<NamedProfile> out = {NamedProfile{}};
  for (const store::StoredProfile& s : *stored) {
    absl::StatusOr<fusion::WeightingProfile> p = fusion::ProfileFromText(s.text);
    if (!p.ok()) return p.status();
    p->name = s.name;
    p->version = s.revision;
    out.push_back({std::move(*p), s.created_utc});
  }
  return out;
}

absl::StatusOr<std::vector<fusion::WeightingProfile>> MaintainedProfiles(
    const store::ProjectStore& store, const store::Manifest& head) {
  std::map<std::string, int32_t> wanted;  // layer name → (name, revision) below
  std::vector<std::pair<std::string, int32_t>> order;
  auto want = [&](const std::string& name, int32_t revision) {
    const std::string layer = store::FusedLayerName(name, revision);
    if (name == fusion::kDefaultProfileName || wanted.count(layer)) return;
    wanted[layer] = revision;
    order.emplace_back(name, revision);
  };
  for (const auto& [key, layers] : head.tiles) {
    for (const auto& [layer, entry] : layers) {
      std::string name;
      int32_t revision = 0;
      if (store::ParseFusedLayerName(layer, &name, &revision)) want(name, revision);
    }
  }
  absl::StatusOr<std::string> active = store.ActiveProfile();
  if (!active.ok()) return active.status();
  if (*active != fusion::kDefaultProfileName) {
    absl::StatusOr<store::StoredProfile> latest = store.GetProfile(*active);
    if (latest.ok()) want(*active, latest->revision);
  }
  std::vector<fusion::WeightingProfile> out;
  for (const auto& [name, revision] : order) {
    absl::StatusOr<NamedProfile> p = LoadProfile(store, name, revision);
    if (!p.ok()) return p.status();
    out.push_back(std::move(p->profile));
  }
  return out;
}

absl::StatusOr<std::map<std::string, records::FusedValues>> FuseProfiles(
    const records::RecordSet& records, size_t vossel_count, double vossel_size_m,
    const std::vector<fusion::WeightingProfile>& profiles) {
  std::map<std::string, records::FusedValues> out;
  for (const fusion::WeightingProfile& p : profiles) {
    absl::StatusOr<records::FusedValues> f = fusion::Fuse(records, vossel_count, vossel_size_m, p);
    if (!f.ok()) return f.status();
    out[store::FusedLayerName(p.name, p.version)] = std::move(*f);
  }
  return out;
}

}  // namespace vasl::reweight
