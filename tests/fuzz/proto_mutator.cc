#include "tests/fuzz/proto_mutator.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include <google/protobuf/descriptor.h>

namespace vasl::fuzz {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::EnumDescriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::Reflection;

/// One place a mutation can happen: a singular field, a repeated field as a whole
/// (index -1) or one element of a repeated scalar field.
struct Slot {
  Message* message;
  const FieldDescriptor* field;
  int index;
};

void CollectSlots(Message* message, int depth, std::vector<Slot>* slots) {
  const Descriptor* descriptor = message->GetDescriptor();
  const Reflection* reflection = message->GetReflection();
  for (int i = 0; i < descriptor->field_count(); ++i) {
    const FieldDescriptor* field = descriptor->field(i);
    const bool is_message = field->cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE;
    if (field->is_repeated()) {
      slots->push_back({message, field, -1});
      const int n = reflection->FieldSize(*message, field);
      for (int k = 0; k < n; ++k) {
        if (is_message) {
          if (depth < 8) CollectSlots(reflection->MutableRepeatedMessage(message, field, k),
                                      depth + 1, slots);
        } else {
          slots->push_back({message, field, k});
        }
      }
    } else {
      slots->push_back({message, field, -1});
      if (is_message && depth < 8 && reflection->HasField(*message, field)) {
        CollectSlots(reflection->MutableMessage(message, field), depth + 1, slots);
      }
    }
  }
}

int64_t MutateInt(int64_t value, std::minstd_rand& rng) {
  static const int64_t kSpecial[] = {
      0, 1, -1, 2, 3, 4, 7, 8, 15, 16, 17, 27, 28, 29, 32, 56, 255, 256, 1023, 1024, 4095,
      4096, 4097, 16383, 16384, 16385, 65535, 65536, 65537, int64_t{1} << 20,
      std::numeric_limits<int32_t>::max(), std::numeric_limits<int32_t>::min(),
      int64_t{1} << 31, int64_t{1} << 32, std::numeric_limits<int64_t>::max(),
      std::numeric_limits<int64_t>::min(), std::numeric_limits<int64_t>::max() / 16,
      std::numeric_limits<int64_t>::max() / 28 + 1};
  switch (rng() % 6) {
    case 0:  // a small step, wrapping as the wire would rather than overflowing
      return static_cast<int64_t>(static_cast<uint64_t>(value) + (rng() % 33) - 16);
    case 1: return static_cast<int64_t>(static_cast<uint64_t>(value) * 2);
    case 2: return value / 2;
    case 3: return static_cast<int64_t>(0 - static_cast<uint64_t>(value));
    case 4: return static_cast<int64_t>((uint64_t{rng()} << 32) ^ rng());
    default: return kSpecial[rng() % (sizeof(kSpecial) / sizeof(kSpecial[0]))];
  }
}

double MutateDouble(double value, std::minstd_rand& rng) {
  static const double kSpecial[] = {0.0,
                                    -0.0,
                                    1.0,
                                    -1.0,
                                    0.5,
                                    2.0,
                                    3e-4,
                                    0.1,
                                    std::nextafter(0.1, 1.0),
                                    1e-300,
                                    1e300,
                                    std::numeric_limits<double>::denorm_min(),
                                    std::numeric_limits<double>::max(),
                                    std::numeric_limits<double>::lowest(),
                                    std::numeric_limits<double>::quiet_NaN(),
                                    std::numeric_limits<double>::infinity(),
                                    -std::numeric_limits<double>::infinity()};
  switch (rng() % 4) {
    case 0: return value * (static_cast<double>(rng() % 2001) / 1000.0 - 1.0);
    case 1: return value + (static_cast<double>(rng() % 2001) / 1000.0 - 1.0);
    case 2: return std::nextafter(value, rng() % 2 ? 1e308 : -1e308);
    default: return kSpecial[rng() % (sizeof(kSpecial) / sizeof(kSpecial[0]))];
  }
}

int MutateEnum(const EnumDescriptor* type, std::minstd_rand& rng) {
  if (rng() % 4 == 0) {
    static const int kOutOfRange[] = {-1, 99, 1000, std::numeric_limits<int32_t>::max()};
    return kOutOfRange[rng() % 4];
  }
  return type->value(static_cast<int>(rng() % static_cast<unsigned>(type->value_count())))
      ->number();
}

std::string MutateBytes(std::string bytes, bool utf8, std::minstd_rand& rng,
                        const BytesMutator& mutate_bytes, size_t max_growth) {
  if (!utf8 && rng() % 4 == 0) {
    // Resize by a multiple of 4 bytes (one float): moves a PointsChunk across the 16/28 sizes.
    const int64_t delta = 4 * (static_cast<int64_t>(rng() % 17) - 8);
    const int64_t size = std::max<int64_t>(0, static_cast<int64_t>(bytes.size()) + delta);
    bytes.resize(static_cast<size_t>(std::min<int64_t>(
        size, static_cast<int64_t>(bytes.size() + max_growth))), '\0');
    return bytes;
  }
  const size_t size = bytes.size();
  bytes.resize(size + max_growth);
  bytes.resize(mutate_bytes(reinterpret_cast<uint8_t*>(bytes.data()), size, bytes.size()));
  if (utf8 && rng() % 4 != 0) {
    // Mostly keep proto3 strings parseable: invalid UTF-8 fails the parse before the server.
    for (char& c : bytes) c = static_cast<char>(c & 0x7f);
  }
  return bytes;
}

void MutateScalar(const Slot& slot, std::minstd_rand& rng, const BytesMutator& mutate_bytes,
                  size_t max_growth) {
  Message* m = slot.message;
  const FieldDescriptor* f = slot.field;
  const Reflection* r = m->GetReflection();
  const bool rep = slot.index >= 0;
  const int k = slot.index;
  switch (f->cpp_type()) {
    case FieldDescriptor::CPPTYPE_INT32: {
      const int64_t v = rep ? r->GetRepeatedInt32(*m, f, k) : r->GetInt32(*m, f);
      const auto next = static_cast<int32_t>(MutateInt(v, rng));
      rep ? r->SetRepeatedInt32(m, f, k, next) : r->SetInt32(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_INT64: {
      const int64_t v = rep ? r->GetRepeatedInt64(*m, f, k) : r->GetInt64(*m, f);
      const int64_t next = MutateInt(v, rng);
      rep ? r->SetRepeatedInt64(m, f, k, next) : r->SetInt64(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_UINT32: {
      const int64_t v = rep ? r->GetRepeatedUInt32(*m, f, k) : r->GetUInt32(*m, f);
      const auto next = static_cast<uint32_t>(MutateInt(v, rng));
      rep ? r->SetRepeatedUInt32(m, f, k, next) : r->SetUInt32(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_UINT64: {
      const auto v = static_cast<int64_t>(rep ? r->GetRepeatedUInt64(*m, f, k) : r->GetUInt64(*m, f));
      const auto next = static_cast<uint64_t>(MutateInt(v, rng));
      rep ? r->SetRepeatedUInt64(m, f, k, next) : r->SetUInt64(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_DOUBLE: {
      const double v = rep ? r->GetRepeatedDouble(*m, f, k) : r->GetDouble(*m, f);
      const double next = MutateDouble(v, rng);
      rep ? r->SetRepeatedDouble(m, f, k, next) : r->SetDouble(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_FLOAT: {
      const double v = rep ? r->GetRepeatedFloat(*m, f, k) : r->GetFloat(*m, f);
      const auto next = static_cast<float>(MutateDouble(v, rng));
      rep ? r->SetRepeatedFloat(m, f, k, next) : r->SetFloat(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_BOOL: {
      const bool v = rep ? r->GetRepeatedBool(*m, f, k) : r->GetBool(*m, f);
      rep ? r->SetRepeatedBool(m, f, k, !v) : r->SetBool(m, f, !v);
      break;
    }
    case FieldDescriptor::CPPTYPE_ENUM: {
      const int next = MutateEnum(f->enum_type(), rng);
      rep ? r->SetRepeatedEnumValue(m, f, k, next) : r->SetEnumValue(m, f, next);
      break;
    }
    case FieldDescriptor::CPPTYPE_STRING: {
      const bool utf8 = f->type() == FieldDescriptor::TYPE_STRING;
      std::string v = rep ? r->GetRepeatedString(*m, f, k) : r->GetString(*m, f);
      v = MutateBytes(std::move(v), utf8, rng, mutate_bytes, max_growth);
      rep ? r->SetRepeatedString(m, f, k, std::move(v)) : r->SetString(m, f, std::move(v));
      break;
    }
    case FieldDescriptor::CPPTYPE_MESSAGE:
      break;  // handled by the caller
  }
}

void MutateRepeated(const Slot& slot, std::minstd_rand& rng) {
  Message* m = slot.message;
  const FieldDescriptor* f = slot.field;
  const Reflection* r = m->GetReflection();
  const int n = r->FieldSize(*m, f);
  const unsigned action = n == 0 ? 0 : rng() % 4;
  if (action == 0 && n < 32) {  // add an element: a copy of one, or a default one
    if (f->cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE) {
      Message* added = r->AddMessage(m, f);
      if (n > 0 && rng() % 2 == 0) {
        added->CopyFrom(r->GetRepeatedMessage(*m, f, static_cast<int>(rng() % unsigned(n))));
      }
      return;
    }
    switch (f->cpp_type()) {
      case FieldDescriptor::CPPTYPE_INT32: r->AddInt32(m, f, 0); break;
      case FieldDescriptor::CPPTYPE_INT64: r->AddInt64(m, f, 0); break;
      case FieldDescriptor::CPPTYPE_UINT32: r->AddUInt32(m, f, 0); break;
      case FieldDescriptor::CPPTYPE_UINT64: r->AddUInt64(m, f, 0); break;
      case FieldDescriptor::CPPTYPE_DOUBLE: r->AddDouble(m, f, 0.0); break;
      case FieldDescriptor::CPPTYPE_FLOAT: r->AddFloat(m, f, 0.0f); break;
      case FieldDescriptor::CPPTYPE_BOOL: r->AddBool(m, f, true); break;
      case FieldDescriptor::CPPTYPE_ENUM: r->AddEnumValue(m, f, MutateEnum(f->enum_type(), rng)); break;
      case FieldDescriptor::CPPTYPE_STRING: r->AddString(m, f, "x"); break;
      case FieldDescriptor::CPPTYPE_MESSAGE: break;
    }
  } else if (action == 1 && n > 0) {
    r->RemoveLast(m, f);
  } else if (action == 2 && n > 1) {
    r->SwapElements(m, f, static_cast<int>(rng() % unsigned(n)), static_cast<int>(rng() % unsigned(n)));
  } else if (n > 0 && rng() % 4 == 0) {
    r->ClearField(m, f);
  }
}

}  // namespace

void MutateMessage(Message* message, std::minstd_rand& rng, const BytesMutator& mutate_bytes,
                   size_t max_growth) {
  std::vector<Slot> slots;
  CollectSlots(message, 0, &slots);
  if (slots.empty()) return;
  const Slot& slot = slots[rng() % slots.size()];
  const Reflection* r = slot.message->GetReflection();
  if (slot.field->is_repeated() && slot.index < 0) {
    MutateRepeated(slot, rng);
  } else if (slot.field->cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE) {
    if (r->HasField(*slot.message, slot.field)) {
      if (rng() % 4 == 0) r->ClearField(slot.message, slot.field);
    } else {
      r->MutableMessage(slot.message, slot.field);  // set an absent message (or oneof member)
    }
  } else {
    MutateScalar(slot, rng, mutate_bytes, max_growth);
  }
}

}  // namespace vasl::fuzz
