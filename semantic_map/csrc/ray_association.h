// Ray -> frontier association kernels of semantic_map._rfkernels (ray_association.cpp).
#pragma once

#include <nanobind/nanobind.h>

// Adds associate_rays and argmin_cost to the module.
void register_ray_association(nanobind::module_& m);
