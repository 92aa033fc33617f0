// Input array types of the semantic_map._rfkernels functions: C-contiguous CPU arrays.
#pragma once

#include <cstdint>

#include <nanobind/ndarray.h>

namespace rfk::arrays {

using I64In = nanobind::ndarray<const int64_t, nanobind::ndim<1>, nanobind::c_contig, nanobind::device::cpu>;
using F64In = nanobind::ndarray<const double, nanobind::ndim<1>, nanobind::c_contig, nanobind::device::cpu>;
using F32In = nanobind::ndarray<const float, nanobind::ndim<1>, nanobind::c_contig, nanobind::device::cpu>;
using F64x3In = nanobind::ndarray<const double, nanobind::shape<-1, 3>, nanobind::c_contig, nanobind::device::cpu>;
using I64x3In = nanobind::ndarray<const int64_t, nanobind::shape<-1, 3>, nanobind::c_contig, nanobind::device::cpu>;

}  // namespace rfk::arrays
