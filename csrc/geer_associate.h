// Stage 2 math shared by csrc/associate.cu and the CPU build: which tiles a Gaussian's PBF overlaps,
// found in O(log T + hits) per Gaussian on every ray grid, and the (tile, depth) sort key.
//
// The twin (geer_ns/render/associate.py) is the specification: a tile is hit when it is active and its
// mirror-tangent theta and phi bounds both overlap the PBF's interval pieces (split at the +-pi seam).
// The search runs over a pyramid of tile blocks (raygrid.RayGrid.tile_pyramid): level 0 holds the tiles,
// each level above holds 2x2 blocks of the one below with the union of their active tiles' bounds, the
// top level one node with the grid's overall bounds (the O(1) reject of Gaussians outside the view, e.g.
// behind a 180-degree camera). A node that does not overlap the PBF has no hit below it, so the search
// only descends where tiles can be hit; a leaf is tested with the tile's own bounds, so the hits are
// exactly the twin's. Works for any grid (BEAP with masked tiles, native fisheye, equirectangular).
//
// Count pass: the pyramid search, counting hits and recording their tile bounding box. Emit pass:
// only that box is visited (no second search), in increasing tile order. Both report their tile tests.
#pragma once

#include "geer_math.h"

namespace geer {

// ---------------------------------------------------------------------------------- tile pyramid
constexpr int kMaxPyramidLevels = 17;  // up to 2^16 tiles along an axis

// Level sizes of the pyramid over a tiles_x x tiles_y grid (raygrid.pyramid_levels computes the same):
// level l is ceil(tiles / 2^l) along each axis, nodes stored level by level, row-major within a level.
struct TilePyramid {
    int levels;  // level 0: the tiles; level levels - 1: a single node
    int nx[kMaxPyramidLevels], ny[kMaxPyramidLevels], offset[kMaxPyramidLevels];
    int n_nodes;
};

GEER_HD TilePyramid make_tile_pyramid(int tiles_x, int tiles_y) {
    TilePyramid p;
    int nx = tiles_x, ny = tiles_y, off = 0, l = 0;
    for (;;) {
        p.nx[l] = nx;
        p.ny[l] = ny;
        p.offset[l] = off;
        off += nx * ny;
        ++l;
        if ((nx <= 1 && ny <= 1) || l == kMaxPyramidLevels) break;
        nx = (nx + 1) / 2;
        ny = (ny + 1) / 2;
    }
    p.levels = l;
    p.n_nodes = off;
    return p;
}

// The pyramid's per-node data: bounds [n_nodes][4] (theta lo, hi, phi lo, hi, mirror domain; level 0 =
// the tiles' own bounds) and whether any tile below the node is active.
template <typename T> struct PyramidNodes {
    const T* bounds;
    const uint8_t* active;
};

template <typename T> GEER_HD bool node_hit(const PbfPieces<T>& p, const PyramidNodes<T>& nodes, int node) {
    if (!nodes.active[node]) return false;
    return pbf_overlaps(p, nodes.bounds + 4 * node);
}

// Inclusive tile-coordinate box of a Gaussian's hits, packed in 64 bits (16 bits per coordinate).
struct TileBox {
    int x0, y0, x1, y1;  // empty: x0 > x1
};
GEER_HD uint64_t pack_box(const TileBox& b) {
    return uint64_t(uint16_t(b.x0)) | (uint64_t(uint16_t(b.x1)) << 16) | (uint64_t(uint16_t(b.y0)) << 32) |
           (uint64_t(uint16_t(b.y1)) << 48);
}
GEER_HD TileBox unpack_box(uint64_t v) {
    return TileBox{int(v & 0xffff), int((v >> 32) & 0xffff), int((v >> 16) & 0xffff), int((v >> 48) & 0xffff)};
}

// Count pass for one Gaussian: the number of tiles hit, their bounding box and the tile tests spent
// (every node tested, the top node included). Depth-first with an explicit stack (no recursion on the GPU).
template <typename T>
GEER_HD int count_overlapping_tiles(const T* pbf_bounds, bool alive, const TilePyramid& pyr,
                                    const PyramidNodes<T>& nodes, int* tests, TileBox* box) {
    *tests = 0;
    *box = TileBox{1, 1, 0, 0};
    if (!alive || pyr.n_nodes == 0) return 0;
    const PbfPieces<T> p = pbf_pieces(pbf_bounds);
    const int top = pyr.levels - 1;
    *tests = 1;
    if (!node_hit(p, nodes, pyr.offset[top])) return 0;  // outside the grid's overall bounds
    int stack_level[4 * kMaxPyramidLevels], stack_idx[4 * kMaxPyramidLevels];
    int sp = 0, count = 0, n_tests = 1;
    stack_level[sp] = top;
    stack_idx[sp++] = 0;
    while (sp > 0) {
        --sp;
        const int l = stack_level[sp], idx = stack_idx[sp];
        const int x = idx % pyr.nx[l], y = idx / pyr.nx[l];
        if (l == 0) {  // a tile that is hit
            if (count == 0) *box = TileBox{x, y, x, y};
            box->x0 = g_min(box->x0, x); box->x1 = g_max(box->x1, x);
            box->y0 = g_min(box->y0, y); box->y1 = g_max(box->y1, y);
            ++count;
            continue;
        }
        const int cl = l - 1, cnx = pyr.nx[cl], cny = pyr.ny[cl];
        for (int c = 0; c < 4; ++c) {
            const int cx = 2 * x + (c & 1), cy = 2 * y + (c >> 1);
            if (cx >= cnx || cy >= cny) continue;
            const int cidx = cy * cnx + cx;
            ++n_tests;
            if (!node_hit(p, nodes, pyr.offset[cl] + cidx)) continue;
            stack_level[sp] = cl;
            stack_idx[sp++] = cidx;
        }
    }
    *tests = n_tests;
    return count;
}

// Emit pass for one Gaussian: f(tile) for every tile hit, in increasing tile order, visiting only the box
// the count pass found. Returns the tile tests spent.
template <typename T, typename F>
GEER_HD int emit_overlapping_tiles(const T* pbf_bounds, const TileBox& box, int tiles_x, const PyramidNodes<T>& nodes,
                                   F&& f) {
    if (box.x0 > box.x1) return 0;
    const PbfPieces<T> p = pbf_pieces(pbf_bounds);
    for (int y = box.y0; y <= box.y1; ++y)
        for (int x = box.x0; x <= box.x1; ++x) {
            const int tile = y * tiles_x + x;  // level 0 of the pyramid: node = tile
            if (node_hit(p, nodes, tile)) f(tile);
        }
    return (box.x1 - box.x0 + 1) * (box.y1 - box.y0 + 1);
}

// Sort key of one (tile, Gaussian) pair: tile in the high 32 bits, the Gaussian's depth order in the low
// 32: the bits of its float32 depth (non-negative floats order like their bits) or, for float64, its rank
// in the twin's stable depth sort. A stable sort of pairs emitted in Gaussian order then breaks depth
// ties by index, exactly the twin's order.
GEER_HD constexpr uint64_t pair_key(int tile, uint32_t order) { return (uint64_t(uint32_t(tile)) << 32) | uint64_t(order); }
GEER_HD constexpr int key_tile(uint64_t key) { return int(uint32_t(key >> 32)); }

// A tile's list starts where the tile id changes in the sorted keys and ends where the next one starts.
GEER_HD void mark_tile_range(const uint64_t* sorted_keys, int64_t m, int64_t i, int32_t* ranges) {
    const int tile = key_tile(sorted_keys[i]);
    if (i == 0 || key_tile(sorted_keys[i - 1]) != tile) ranges[2 * tile] = int32_t(i);
    if (i == m - 1 || key_tile(sorted_keys[i + 1]) != tile) ranges[2 * tile + 1] = int32_t(i + 1);
}

}  // namespace geer
