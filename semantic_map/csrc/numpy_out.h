// Hand a std::vector to numpy without copying: the vector moves to the heap, owned by a
// capsule that numpy keeps alive. Needs the GIL. Shared by _rfkernels and _vdbocc.
#pragma once

#include <initializer_list>
#include <vector>

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

template <typename T>
nanobind::ndarray<nanobind::numpy, T> to_numpy(std::vector<T>&& v, std::initializer_list<size_t> shape) {
    if (v.capacity() == 0) v.reserve(1);  // never hand out a null data pointer
    auto* heap = new std::vector<T>(std::move(v));
    nanobind::capsule owner(heap, [](void* p) noexcept { delete static_cast<std::vector<T>*>(p); });
    return nanobind::ndarray<nanobind::numpy, T>(heap->data(), shape, owner);
}
