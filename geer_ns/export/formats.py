"""Writers of the three Gaussian-splat files viewers read: the 3DGS PLY, glTF KHR_gaussian_splatting (.glb) and
Niantic's SPZ (version 3, gzip). Written from the formats' specifications (docs/export.md lists them and what
each stores, with the round-trip error the tests measure).

Every writer takes a `Splats` in splatfacto's parameterization (log-scales, opacity logits, SH with the DC term
first) and a metadata dict saying how the scene was trained, which each format keeps where it can. Each format
holds one SH degree for all its Gaussians: with per-Gaussian degrees (geer_ns/sh_degrees) the files store the
highest degree any Gaussian keeps, a lower-degree Gaussian's higher coefficients as the zeros they are.
"""

from __future__ import annotations

import gzip
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

SH_C0 = 0.28209479177387814
SPZ_MAGIC = 0x5053474E  # "NGSP"
SPZ_COLOR_SCALE = 0.15  # SPZ stores 0.5 + 0.15 * DC in a byte (room for colors beyond [0, 1])
SPZ_FRACTIONAL_BITS = 12  # positions in 1/4096 units, up to +-2048 units
# glTF's +Y up from nerfstudio's +Z up: the node's rotation, -90 degrees about x (x, y, z) -> (x, z, -y), as
# a quaternion (x, y, z, w). The splats themselves stay in nerfstudio's world frame.
Z_UP_TO_Y_UP = [-(0.5 ** 0.5), 0.0, 0.0, 0.5 ** 0.5]


@dataclass
class Splats:
    """Gaussians as splatfacto stores them, as float32 numpy arrays."""

    means: np.ndarray  # [N, 3]
    log_scales: np.ndarray  # [N, 3]
    quats_wxyz: np.ndarray  # [N, 4] any norm
    opacity_logits: np.ndarray  # [N]
    sh_dc: np.ndarray  # [N, 3] SH degree-0 coefficients (color = 0.5 + SH_C0 * dc)
    sh_rest: np.ndarray  # [N, K, 3] higher-degree coefficients, K = (degree + 1)^2 - 1
    sh_degrees: Optional[np.ndarray] = None  # [N] each Gaussian's own degree (its higher coefficients are zero)

    @property
    def count(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """The degree the files store for every Gaussian (each format has one per file): the highest any
        Gaussian keeps; a Gaussian of a lower degree stores zeros above it, which is what it has."""
        held = int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1
        if self.sh_degrees is None or self.count == 0:
            return held
        return min(held, int(self.sh_degrees.max()))

    def rest(self) -> np.ndarray:
        """[N, (sh_degree + 1)^2 - 1, 3] the higher-degree coefficients the files store."""
        return self.sh_rest[:, : (self.sh_degree + 1) ** 2 - 1]

    def unit_quats(self) -> np.ndarray:
        q = self.quats_wxyz.astype(np.float64)
        return q / np.linalg.norm(q, axis=-1, keepdims=True)

    def opacities(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))


# --------------------------------------------------------------------------------------------- PLY
def write_ply(splats: Splats, path: Path, metadata: dict) -> None:
    """The 3DGS PLY (as ns-export gaussian-splat and the original 3DGS): x y z, nx ny nz (0), f_dc_0..2,
    f_rest_* channel-major (all of R's coefficients, then G's, then B's), opacity (logit), scale_0..2 (log),
    rot_0..3 (wxyz). The metadata goes into `comment` lines of the header."""
    from plyfile import PlyData, PlyElement

    n, k = splats.count, splats.rest().shape[1]
    columns = {"x": splats.means[:, 0], "y": splats.means[:, 1], "z": splats.means[:, 2],
               "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    columns.update({f"f_dc_{c}": splats.sh_dc[:, c] for c in range(3)})
    rest = splats.rest().transpose(0, 2, 1).reshape(n, 3 * k)  # channel-major
    columns.update({f"f_rest_{i}": rest[:, i] for i in range(3 * k)})
    columns["opacity"] = splats.opacity_logits
    columns.update({f"scale_{i}": splats.log_scales[:, i] for i in range(3)})
    columns.update({f"rot_{i}": splats.quats_wxyz[:, i] for i in range(4)})
    rows = np.empty(n, dtype=[(name, "f4") for name in columns])
    for name, values in columns.items():
        rows[name] = values
    comments = [f"{key}: {value}" for key, value in metadata.items()]
    PlyData([PlyElement.describe(rows, "vertex")], comments=comments).write(str(path))


# --------------------------------------------------------------------------------------------- GLB
def _accessor(blob: bytearray, views: list, accessors: list, values: np.ndarray, kind: str, minmax=False) -> int:
    """Append float32 `values` [N, C] as a buffer view + accessor of type `kind`; returns the accessor index."""
    data = np.ascontiguousarray(values, dtype="<f4")
    while len(blob) % 4:
        blob.append(0)
    views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes})
    blob.extend(data.tobytes())
    accessor = {"bufferView": len(views) - 1, "componentType": 5126, "count": int(data.shape[0]), "type": kind}
    if minmax:  # POSITION requires its bounds
        accessor["min"] = [float(v) for v in data.min(axis=0)]
        accessor["max"] = [float(v) for v in data.max(axis=0)]
    accessors.append(accessor)
    return len(accessors) - 1


def write_glb(splats: Splats, path: Path, metadata: dict) -> None:
    """Binary glTF with one POINTS primitive carrying KHR_gaussian_splatting: POSITION, linear SCALE, ROTATION
    (unit xyzw), OPACITY (in [0, 1]), SH_DEGREE_l_COEF_n (RGB coefficients, the DC term as trained, 0.5 bias
    applied by the renderer), COLOR_0 (the diffuse color and opacity, for viewers without the extension).
    The node rotates nerfstudio's +Z up to glTF's +Y up; the metadata goes into asset.extras."""
    blob: bytearray = bytearray()
    views: list = []
    accessors: list = []
    prefix = "KHR_gaussian_splatting:"
    quats = splats.unit_quats()
    opacity = splats.opacities()
    color = np.clip(0.5 + SH_C0 * splats.sh_dc.astype(np.float64), 0.0, 1.0)
    attributes = {
        "POSITION": _accessor(blob, views, accessors, splats.means, "VEC3", minmax=True),
        prefix + "SCALE": _accessor(blob, views, accessors, np.exp(splats.log_scales.astype(np.float64)), "VEC3"),
        prefix + "ROTATION": _accessor(blob, views, accessors, quats[:, [1, 2, 3, 0]], "VEC4"),
        prefix + "OPACITY": _accessor(blob, views, accessors, opacity[:, None], "SCALAR"),
        prefix + "SH_DEGREE_0_COEF_0": _accessor(blob, views, accessors, splats.sh_dc, "VEC3"),
        "COLOR_0": _accessor(blob, views, accessors, np.concatenate([color, opacity[:, None]], -1), "VEC4"),
    }
    index = 0
    for degree in range(1, splats.sh_degree + 1):
        for n in range(2 * degree + 1):
            attributes[f"{prefix}SH_DEGREE_{degree}_COEF_{n}"] = _accessor(
                blob, views, accessors, splats.rest()[:, index], "VEC3")
            index += 1
    extension = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
                 "sortingMethod": "cameraDistance"}
    while len(blob) % 4:
        blob.append(0)
    gltf = {
        "asset": {"version": "2.0", "generator": "geer-ns geer-export", "extras": metadata},
        "extensionsUsed": ["KHR_gaussian_splatting"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "rotation": Z_UP_TO_Y_UP, "name": "geer_splats"}],
        "meshes": [{"primitives": [{"attributes": attributes, "mode": 0,
                                    "extensions": {"KHR_gaussian_splatting": extension}}]}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, total))  # "glTF", version 2
        f.write(struct.pack("<II", len(text), 0x4E4F534A) + text)  # JSON chunk
        f.write(struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))  # BIN chunk


# --------------------------------------------------------------------------------------------- SPZ
def _quantize(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip(np.rint(values), lo, hi).astype(np.uint8)


def _smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32: SPZ v3 rotations. Components (x, y, z, w); the largest's index in the top 2 bits, the other
    three, in axis order, as 10 bits each (sign bit over a 9-bit magnitude in units of 1/sqrt(2) / 511), the
    last axis in the lowest bits; the quaternion's sign is chosen so that the largest component is positive."""
    q = quats_wxyz[:, [1, 2, 3, 0]]
    largest = np.abs(q).argmax(axis=1)
    q = np.where(q[np.arange(len(q)), largest][:, None] < 0, -q, q)
    packed = np.zeros(len(q), dtype=np.uint64)
    for axis in range(4):
        keep = largest != axis
        value = q[:, axis]
        magnitude = np.clip(np.rint(np.abs(value) * (2 ** 0.5) * 511), 0, 511).astype(np.uint64)
        word = magnitude | ((value < 0).astype(np.uint64) << np.uint64(9))
        packed = np.where(keep, (packed << np.uint64(10)) | word, packed)
    packed |= largest.astype(np.uint64) << np.uint64(30)
    return packed.astype(np.uint32)


def write_spz(splats: Splats, path: Path, metadata: dict) -> None:
    """SPZ version 3: a gzip stream of a 16-byte header (magic, version, count, SH degree, fractional bits,
    flags, reserved) and the attributes in turn: positions (24-bit fixed point), alphas (opacity * 255),
    colors (0.5 + 0.15 DC, * 255), scales ((log + 10) * 16), rotations (smallest three), SH (coefficient-major,
    channel inner, 128 + 128 x). Coordinates unconverted (nerfstudio's world frame). SPZ has no metadata field;
    `metadata` is written beside it as `<path>.json`."""
    n = splats.count
    degree = min(splats.sh_degree, 3)
    fixed = np.rint(splats.means.astype(np.float64) * (1 << SPZ_FRACTIONAL_BITS)).astype(np.int64)
    limit = (1 << 23) - 1
    if np.abs(fixed).max(initial=0) > limit:
        raise ValueError(f"{path}: positions beyond +-{limit / (1 << SPZ_FRACTIONAL_BITS):.0f} units do not fit "
                         "SPZ's 24-bit fixed point at 12 fractional bits")
    fixed = fixed & 0xFFFFFF
    positions = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], -1).astype(np.uint8).reshape(n, 9)
    alphas = _quantize(splats.opacities() * 255.0, 0, 255)
    colors = _quantize((0.5 + SPZ_COLOR_SCALE * splats.sh_dc.astype(np.float64)) * 255.0, 0, 255)
    scales = _quantize((splats.log_scales.astype(np.float64) + 10.0) * 16.0, 0, 255)
    rotations = _smallest_three(splats.unit_quats()).astype("<u4").view(np.uint8).reshape(n, 4)
    k = (degree + 1) ** 2 - 1
    sh = _quantize(splats.rest()[:, :k].astype(np.float64) * 128.0 + 128.0, 0, 255).reshape(n, 3 * k)
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, 3, n, degree, SPZ_FRACTIONAL_BITS, 0, 0)
    payload = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh))
    with gzip.open(path, "wb") as f:
        f.write(header + payload)
    Path(f"{path}.json").write_text(json.dumps(metadata, indent=2) + "\n")


WRITERS = {"ply": write_ply, "glb": write_glb, "spz": write_spz}
