// The one way to split host work over threads: blockhash_cl/parallel.hpp (public, so that the
// renderer and the benchmarks use it too).
#pragma once

#include "blockhash_cl/parallel.hpp"
