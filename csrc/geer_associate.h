// Stage 2 math shared by csrc/associate.cu and the CPU build: which tiles a Gaussian's PBF overlaps,
// found in O(log T + hits) per Gaussian on every ray grid, and the (tile, depth) sort key.
//
// The twin (geer_ns/render/associate.py) is the specification: a tile is hit when it is active and its
// mirror-tangent theta and phi bounds both overlap the PBF's interval pieces (split at the +-pi seam) and, where
// cones are given, its cone meets the Gaussian's (cone_meets_tile, tested on the box test's survivors only).
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

// ---------------------------------------------------------------------------------- the cone test
// A test whose tightness does not depend on where the tile sits (derivation: docs/association.md). A Gaussian's
// alpha >= 1/255 directions lie in the elliptic cone F(d) = (a.d)^2 - (b1.d)^2 - (b2.d)^2 >= 0 (cones.py
// gaussian_cone_form: a = lambda W^T o_hat, b_i = sqrt(|o_u|^2 - lambda^2) W^T p_i, all zero where the camera is
// inside); a tile's rays lie within angle beta of its centre ray c (cones.py tile_cones). On the plane c.d = 1,
// d = c + x1 e1 + x2 e2, the tile's rays fill the disk |x| <= tan(beta) and F is x^T H x + 2 g.x + f0; the tile
// can see the Gaussian only if max over the disk of F >= 0. That maximum is a trust-region problem whose
// Lagrangian dual is exact: U(mu) = f0 + mu tan^2(beta) + g^T (mu I - H)^-1 g bounds it from above for every
// mu >= max(0, h1) (h1: H's larger eigenvalue), so any mu gives a conservative reject (U < 0); a few Newton
// steps on the secular equation |x(mu)| = tan(beta) bring mu near the minimiser, where the test is exact.
constexpr int kGaussConeValues = 9;   // a, b1, b2
constexpr int kTileConeValues = 10;   // e1, e2, c (orthonormal, c the centre ray), tan(beta) (inf: no test)
constexpr int kConeNewtonSteps = 3;
// Reject only below -tol x the magnitude of F's terms on the disk: far above the rounding of either precision.
template <typename T> struct ConeTol { static constexpr double value = sizeof(T) == 4 ? 1e-5 : 1e-12; };

// F's coefficient (i, j) on the tile plane: p[v] = (v.e1, v.e2, v.c) for the rows v = a, b1, b2.
template <typename T> GEER_HD T cone_coef(const T (*p)[3], int i, int j) {
    return x_sub(x_sub(x_mul(p[0][i], p[0][j]), x_mul(p[1][i], p[1][j])), x_mul(p[2][i], p[2][j]));
}

// Whether a Gaussian's cone (gauss [9]) may meet a tile's cone (tile [10]); false only where no ray of the tile
// has alpha >= 1/255. Every product and sum uncontracted (x_*): cones.cone_meets_tile takes the same decisions.
template <typename T> GEER_HD bool cone_meets_tile(const T* gauss, const T* tile) {
    const T rho = tile[9];
    if (!(rho < Limits<T>::inf())) return true;
    T p[3][3];
    for (int v = 0; v < 3; ++v) {
        const Vec3<T> r = load3(gauss + 3 * v);
        for (int j = 0; j < 3; ++j) p[v][j] = x_dot(r, load3(tile + 3 * j));
    }
    const T f0 = cone_coef<T>(p, 2, 2);
    if (f0 >= T(0)) return true;  // the centre ray itself
    const T rho2 = x_mul(rho, rho);
    T mag = T(0);  // sum of the squared projections: bounds each term of F on the disk, / (1 + rho^2)
    for (int v = 0; v < 3; ++v)
        for (int j = 0; j < 3; ++j) mag = x_add(mag, x_mul(p[v][j], p[v][j]));
    const T reject_below = -x_mul(T(ConeTol<T>::value), x_mul(mag, x_add(T(1), rho2)));
    // Cheap pre-reject, no division: on the disk |a.d| <= |p_a3| + rho (|p_a1| + |p_a2|) and
    // |b.d| >= |p_b3| - rho (|p_b1| + |p_b2|), so F <= A^2 - B1^2 - B2^2 there. Settles most far pairs.
    T ab[3];
    for (int v = 0; v < 3; ++v) {
        const T spread = x_mul(rho, x_add(g_abs(p[v][0]), g_abs(p[v][1])));
        ab[v] = v == 0 ? x_add(g_abs(p[v][2]), spread) : g_max(x_sub(g_abs(p[v][2]), spread), T(0));
    }
    if (x_sub(x_sub(x_mul(ab[0], ab[0]), x_mul(ab[1], ab[1])), x_mul(ab[2], ab[2])) < reject_below) return false;
    const T h11 = cone_coef<T>(p, 0, 0), h12 = cone_coef<T>(p, 0, 1), h22 = cone_coef<T>(p, 1, 1);
    const T g1 = cone_coef<T>(p, 0, 2), g2 = cone_coef<T>(p, 1, 2);
    const T gg = x_add(x_mul(g1, g1), x_mul(g2, g2));
    if (gg > T(0)) {  // cheap accept: F's maximum on the disk along g's direction is a point of the disk
        const T ng = g_sqrt(gg);
        const T ghg = x_add(x_add(x_mul(x_mul(h11, g1), g1), x_mul(x_mul(x_mul(T(2), h12), g1), g2)),
                            x_mul(x_mul(h22, g2), g2));
        const T c = ghg / gg;
        const T t = c >= T(0) ? rho : g_min(rho, ng / -c);
        if (x_add(x_add(f0, x_mul(x_mul(T(2), t), ng)), x_mul(x_mul(t, t), c)) >= T(0)) return true;
    }
    // H's eigenvalues h1 >= h2 and g's squared components along their eigenvectors.
    const T hm = x_mul(T(0.5), x_add(h11, h22)), hd = x_mul(T(0.5), x_sub(h11, h22));
    const T dd = g_sqrt(x_add(x_mul(hd, hd), x_mul(h12, h12)));
    const T h1 = x_add(hm, dd), h2 = x_sub(hm, dd);
    const T v0 = hd >= T(0) ? x_add(hd, dd) : h12, v1 = hd >= T(0) ? h12 : x_sub(dd, hd);
    const T vn = g_sqrt(x_add(x_mul(v0, v0), x_mul(v1, v1)));
    const T gp = vn > T(0) ? x_add(x_mul(v0, g1), x_mul(v1, g2)) / vn : g1;
    const T q1 = x_mul(gp, gp), q2 = g_max(x_sub(gg, q1), T(0));
    // The minimiser of U lies in [mu_a, mu_b]: |x(mu)| >= tan(beta) at mu_a, <= at mu_b.
    const T mu_lo = g_max(h1, T(0));
    const T mu_a = g_max(mu_lo, x_add(h1, g_abs(gp) / rho)), mu_b = g_max(mu_lo, x_add(h1, g_sqrt(gg) / rho));
    T mu = mu_a;
    for (int it = 0; it < kConeNewtonSteps; ++it) {  // Newton on 1 / |x(mu)| - 1 / tan(beta), from the left
        const T t1 = x_sub(mu, h1), t2 = x_sub(mu, h2);
        const T s1 = q1 / x_mul(t1, t1), s2 = q2 / x_mul(t2, t2);
        const T n2 = x_add(s1, s2);
        if (!(t1 > T(0)) || !(n2 > rho2) || !(n2 < Limits<T>::inf())) break;
        const T n1 = g_sqrt(n2);
        const T slope = x_add(s1 / t1, s2 / t2) / x_mul(n2, n1);
        const T phi = x_sub(T(1) / n1, T(1) / rho);
        mu = g_min(x_sub(mu, phi / slope), mu_b);
    }
    const T t1 = x_sub(mu, h1), t2 = x_sub(mu, h2);
    if (!(t1 > T(0)) && q1 > T(0)) return true;  // mu on the pole with weight there: no finite bound
    const T u1 = t1 > T(0) ? q1 / t1 : T(0), u2 = t2 > T(0) ? q2 / t2 : T(0);
    const T bound = x_add(x_add(x_add(f0, x_mul(mu, rho2)), u1), u2);
    return bound >= reject_below;
}

// The pyramid's per-node data: bounds [n_nodes][4] (theta lo, hi, phi lo, hi, mirror domain; level 0 =
// the tiles' own bounds), whether any tile below the node is active, and the tiles' cones [n_tiles][10]
// (null: the box test alone).
template <typename T> struct PyramidNodes {
    const T* bounds;
    const uint8_t* active;
    const T* tile_cones;
};

template <typename T> GEER_HD bool node_hit(const PbfPieces<T>& p, const PyramidNodes<T>& nodes, int node) {
    if (!nodes.active[node]) return false;
    return pbf_overlaps(p, nodes.bounds + 4 * node);
}

// A tile (level 0: node = tile) is hit when its box overlaps the PBF and its cone meets the Gaussian's (gauss_cone
// [9], null: the box test alone).
template <typename T>
GEER_HD bool tile_hit(const PbfPieces<T>& p, const T* gauss_cone, const PyramidNodes<T>& nodes, int tile) {
    if (!node_hit(p, nodes, tile)) return false;
    if (gauss_cone == nullptr || nodes.tile_cones == nullptr) return true;
    return cone_meets_tile(gauss_cone, nodes.tile_cones + kTileConeValues * tile);
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
GEER_HD int count_overlapping_tiles(const T* pbf_bounds, const T* gauss_cone, bool alive, const TilePyramid& pyr,
                                    const PyramidNodes<T>& nodes, int* tests, TileBox* box) {
    *tests = 0;
    *box = TileBox{1, 1, 0, 0};
    if (!alive || pyr.n_nodes == 0) return 0;
    const PbfPieces<T> p = pbf_pieces(pbf_bounds);
    const int top = pyr.levels - 1;
    *tests = 1;
    const bool hit_top = top == 0 ? tile_hit(p, gauss_cone, nodes, 0) : node_hit(p, nodes, pyr.offset[top]);
    if (!hit_top) return 0;  // outside the grid's overall bounds
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
            if (!(cl == 0 ? tile_hit(p, gauss_cone, nodes, cidx) : node_hit(p, nodes, pyr.offset[cl] + cidx))) continue;
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
GEER_HD int emit_overlapping_tiles(const T* pbf_bounds, const T* gauss_cone, const TileBox& box, int tiles_x,
                                   const PyramidNodes<T>& nodes, F&& f) {
    if (box.x0 > box.x1) return 0;
    const PbfPieces<T> p = pbf_pieces(pbf_bounds);
    for (int y = box.y0; y <= box.y1; ++y)
        for (int x = box.x0; x <= box.x1; ++x) {
            const int tile = y * tiles_x + x;  // level 0 of the pyramid: node = tile
            if (tile_hit(p, gauss_cone, nodes, tile)) f(tile);
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
