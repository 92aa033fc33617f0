// The float16 text-query product of semantic_map._rfkernels (half_scores.cpp).
#pragma once

#include <nanobind/nanobind.h>

// Adds half_scores and half_scores_available to the module.
void register_half_scores(nanobind::module_& m);
