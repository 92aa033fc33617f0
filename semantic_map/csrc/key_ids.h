// Open-addressing hash map int64 key -> dense id, shared by the kernels of semantic_map._rfkernels.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace rfk {

inline uint64_t mix(uint64_t x) {  // splitmix64 finaliser
    x ^= x >> 31;
    x *= 0x7fb5d329728ea185ULL;
    x ^= x >> 27;
    x *= 0x81dadef4bc2dd44dULL;
    x ^= x >> 33;
    return x;
}

// Open-addressing (linear probing) map int64 key -> dense id in first-seen order.
class KeyIds {
public:
    explicit KeyIds(size_t expected) {
        size_t cap = 16;
        while (cap < 2 * expected + 1) cap <<= 1;
        mask_ = cap - 1;
        slot_key_.resize(cap);
        slot_id_.assign(cap, -1);
    }
    // id of key, inserting it if new
    int64_t insert(int64_t key) {
        size_t h = mix(uint64_t(key)) & mask_;
        while (true) {
            int64_t id = slot_id_[h];
            if (id < 0) {
                id = int64_t(keys_.size());
                slot_id_[h] = id;
                slot_key_[h] = key;
                keys_.push_back(key);
                if (keys_.size() * 2 > mask_) grow();
                return id;
            }
            if (slot_key_[h] == key) return id;
            h = (h + 1) & mask_;
        }
    }
    int64_t find(int64_t key) const {
        size_t h = mix(uint64_t(key)) & mask_;
        while (true) {
            int64_t id = slot_id_[h];
            if (id < 0) return -1;
            if (slot_key_[h] == key) return id;
            h = (h + 1) & mask_;
        }
    }
    const std::vector<int64_t>& keys() const { return keys_; }

private:
    void grow() {
        size_t cap = (mask_ + 1) * 2;
        mask_ = cap - 1;
        slot_key_.assign(cap, 0);
        slot_id_.assign(cap, -1);
        for (size_t id = 0; id < keys_.size(); ++id) {
            size_t h = mix(uint64_t(keys_[id])) & mask_;
            while (slot_id_[h] >= 0) h = (h + 1) & mask_;
            slot_id_[h] = int64_t(id);
            slot_key_[h] = keys_[id];
        }
    }
    size_t mask_ = 0;
    std::vector<int64_t> slot_key_;
    std::vector<int64_t> slot_id_;
    std::vector<int64_t> keys_;
};

}  // namespace rfk
