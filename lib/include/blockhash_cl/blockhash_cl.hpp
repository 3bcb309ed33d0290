// blockhash_cl: batched approximate kNN on 3D points with OpenCL kernels. Umbrella header.
#pragma once

#include "blockhash_cl/config.hpp"
#include "blockhash_cl/blockhash.hpp"
#include "blockhash_cl/block_tables.hpp"
#include "blockhash_cl/grid_index.hpp"
#include "blockhash_cl/bruteforce.hpp"
#include "blockhash_cl/error.hpp"
#include "blockhash_cl/factory.hpp"
#if BHCL_HAVE_FLANN
#include "blockhash_cl/flann_index.hpp"
#endif
#include "blockhash_cl/io.hpp"
#include "blockhash_cl/kdtree.hpp"
#include "blockhash_cl/knn.hpp"
#include "blockhash_cl/metrics.hpp"
#include "blockhash_cl/multi_device.hpp"
#include "blockhash_cl/quirks.hpp"
#include "blockhash_cl/reference.hpp"
#include "blockhash_cl/runtime.hpp"
#include "blockhash_cl/spatial_order.hpp"
