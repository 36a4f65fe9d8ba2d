// Binning of the CPU kernel (rasterize_cpu.cpp step 2): the visible Gaussians sorted by view depth,
// then the per-tile lists filled in that order. Every step runs over fixed contiguous chunks, one
// per thread, and has a unique answer (a stable sort, then a stable counting sort by tile), so the
// lists are the same bits for any thread count.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "cpu_support.h"

namespace grp {
namespace cpu {

// What the binning needs of one Gaussian, written by the preprocess (one record per Gaussian,
// half a cache line, so that the depth-ordered gather reads one line per Gaussian).
struct TileFootprint {
  int32_t rect[4];     // minx, miny, maxx, maxy in tiles (max exclusive); empty when culled
  int64_t offset;      // first slot of the Gaussian (offsets[g]); its tile count before that
  int32_t gaussian;    // the Gaussian's index (set in the depth-ordered copy only)
  uint32_t depth_key;  // bits of the view depth z > 0 (their unsigned order is the float order)
};
static_assert(sizeof(TileFootprint) == 32, "two footprints per cache line");

inline int64_t footprint_area(const TileFootprint& f) {
  return (int64_t)(f.rect[2] - f.rect[0]) * (f.rect[3] - f.rect[1]);
}

// Stable LSD radix sort of (keys[i], vals[i]), i < n, by key: 8 bits a pass; a pass whose digit
// is the same for every key is skipped. keys2 / vals2: buffers of n. Returns the sorted values
// (in vals or vals2). Histograms and scatters run over contiguous chunks; within a bucket, the
// items of chunk c precede those of chunk c + 1, so the order is the stable one.
inline const int32_t* radix_sort_by_key(uint32_t* keys, int32_t* vals, uint32_t* keys2,
                                        int32_t* vals2, int64_t n) {
  const int nchunks = num_chunks(n, int64_t(1) << 15);
  std::vector<int64_t> hist((size_t)nchunks * 256);
  for (int pass = 0; pass < 4; ++pass) {
    const int shift = 8 * pass;
    for_each_chunk(nchunks, [&](int c) {
      int64_t* h = hist.data() + 256 * c;
      std::fill(h, h + 256, int64_t(0));
      const int64_t e = chunk_begin(n, c + 1, nchunks);
      for (int64_t i = chunk_begin(n, c, nchunks); i < e; ++i) ++h[(keys[i] >> shift) & 255u];
    });
    // Exclusive prefix in (digit, chunk) order: the first destination of each chunk's digit.
    int64_t total = 0;
    bool trivial = false;
    for (int d = 0; d < 256; ++d) {
      int64_t digit_count = 0;
      for (int c = 0; c < nchunks; ++c) {
        const int64_t count = hist[256 * c + d];
        hist[256 * c + d] = total;
        total += count;
        digit_count += count;
      }
      trivial = trivial || digit_count == n;
    }
    if (trivial) continue;
    for_each_chunk(nchunks, [&](int c) {
      int64_t* dst = hist.data() + 256 * c;
      const int64_t e = chunk_begin(n, c + 1, nchunks);
      for (int64_t i = chunk_begin(n, c, nchunks); i < e; ++i) {
        const int64_t k = dst[(keys[i] >> shift) & 255u]++;
        keys2[k] = keys[i];
        vals2[k] = vals[i];
      }
    });
    std::swap(keys, keys2);
    std::swap(vals, vals2);
  }
  return vals;
}

// Per-tile lists of the visible Gaussians in depth order (a stable counting sort by tile of the
// depth-sorted Gaussians). order[nvis]: visible Gaussians by increasing depth; footprints: per
// Gaussian (offset = first slot); sorted: scratch of nvis records. Writes tile_ranges[tiles + 1]
// and bin[2 R] = (gaussian, slot) per entry, slot = offsets[g] + the tile's position in g's rect
// (row-major), where R = the footprints' total area (the caller's num_rendered).
inline void fill_tile_lists(int grid_x, int64_t num_tiles, const int32_t* order, int64_t nvis,
                            const TileFootprint* footprints, TileFootprint* sorted,
                            int32_t* tile_ranges, int32_t* bin) {
  const int nchunks = num_chunks(nvis, 4096);
  std::vector<int32_t> counts((size_t)nchunks * num_tiles, 0);
  // 1. Gather the footprints in depth order (the only random reads) and count each chunk's
  //    entries per tile.
  for_each_chunk(nchunks, [&](int c) {
    int32_t* cnt = counts.data() + (size_t)c * num_tiles;
    const int64_t e = chunk_begin(nvis, c + 1, nchunks);
    for (int64_t i = chunk_begin(nvis, c, nchunks); i < e; ++i) {
      if (i + 16 < e) __builtin_prefetch(footprints + order[i + 16]);
      TileFootprint f = footprints[order[i]];
      f.gaussian = order[i];
      sorted[i] = f;
      for (int ty = f.rect[1]; ty < f.rect[3]; ++ty)
        for (int tx = f.rect[0]; tx < f.rect[2]; ++tx) ++cnt[(int64_t)ty * grid_x + tx];
    }
  });
  // 2. Tile ranges, and each chunk's first position in each tile (its counts become cursors).
  tile_ranges[0] = 0;
  for (int64_t t = 0; t < num_tiles; ++t) {
    int32_t pos = tile_ranges[t];
    for (int c = 0; c < nchunks; ++c) {
      const int32_t count = counts[(size_t)c * num_tiles + t];
      counts[(size_t)c * num_tiles + t] = pos;
      pos += count;
    }
    tile_ranges[t + 1] = pos;
  }
  // 3. Scatter, each chunk in depth order.
  for_each_chunk(nchunks, [&](int c) {
    int32_t* cursor = counts.data() + (size_t)c * num_tiles;
    const int64_t e = chunk_begin(nvis, c + 1, nchunks);
    for (int64_t i = chunk_begin(nvis, c, nchunks); i < e; ++i) {
      const TileFootprint& f = sorted[i];
      const int w = f.rect[2] - f.rect[0];
      for (int ty = f.rect[1]; ty < f.rect[3]; ++ty) {
        const int64_t row_slot = f.offset + (int64_t)(ty - f.rect[1]) * w - f.rect[0];
        for (int tx = f.rect[0]; tx < f.rect[2]; ++tx) {
          const int32_t pos = cursor[(int64_t)ty * grid_x + tx]++;
          bin[2 * (int64_t)pos] = f.gaussian;
          bin[2 * (int64_t)pos + 1] = (int32_t)(row_slot + tx);
        }
      }
    }
  });
}

}  // namespace cpu
}  // namespace grp
