"""geer-export's files read back by independent readers (plyfile, pygltflib, gsply), each within its format's
stated precision; the EWA comparison's CPU compositing against a direct evaluation; the command on a checkpoint."""

from __future__ import annotations

import gzip
import json
import math

import numpy as np
import pytest
import torch

from geer_ns.export.ewa import PinholeView, compare, ewa_image_cpu
from geer_ns.export.formats import Splats, write_glb, write_ply, write_spz

N, DEGREE = 200, 3
META = {"trained_with": "test", "renderer": "exact_ray_evaluation"}


@pytest.fixture(scope="module")
def splats():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(N, 4)).astype(np.float32)
    return Splats(means=rng.uniform(-5, 5, (N, 3)).astype(np.float32),
                  log_scales=rng.uniform(-6, 1, (N, 3)).astype(np.float32),
                  quats_wxyz=q,
                  opacity_logits=rng.normal(0, 2, N).astype(np.float32),
                  sh_dc=rng.normal(0, 1, (N, 3)).astype(np.float32),
                  sh_rest=rng.uniform(-0.4, 0.4, (N, (DEGREE + 1) ** 2 - 1, 3)).astype(np.float32))


def _same_rotation(a_wxyz, b_wxyz, tol):
    """|<a, b>| close to 1: the same rotation (q and -q are one)."""
    a = a_wxyz / np.linalg.norm(a_wxyz, axis=1, keepdims=True)
    b = b_wxyz / np.linalg.norm(b_wxyz, axis=1, keepdims=True)
    return np.abs(np.abs((a * b).sum(1)) - 1).max() < tol


def test_ply_read_by_plyfile(splats, tmp_path):
    from plyfile import PlyData

    write_ply(splats, tmp_path / "s.ply", META)
    ply = PlyData.read(str(tmp_path / "s.ply"))
    v = ply["vertex"]
    assert len(v) == N
    assert any("exact_ray_evaluation" in c for c in ply.comments)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), splats.means)
    np.testing.assert_array_equal(np.stack([v[f"scale_{i}"] for i in range(3)], 1), splats.log_scales)
    np.testing.assert_array_equal(np.stack([v[f"rot_{i}"] for i in range(4)], 1), splats.quats_wxyz)
    np.testing.assert_array_equal(v["opacity"], splats.opacity_logits)
    k = splats.sh_rest.shape[1]
    rest = np.stack([v[f"f_rest_{i}"] for i in range(3 * k)], 1).reshape(N, 3, k).transpose(0, 2, 1)
    np.testing.assert_array_equal(rest, splats.sh_rest)  # channel-major in the file, as 3DGS writes it


def test_glb_read_by_pygltflib(splats, tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    write_glb(splats, tmp_path / "s.glb", META)
    gltf = pygltflib.GLTF2().load(str(tmp_path / "s.glb"))
    assert "KHR_gaussian_splatting" in gltf.extensionsUsed
    prim = gltf.meshes[0].primitives[0]
    assert prim.mode == 0 and prim.extensions["KHR_gaussian_splatting"]["kernel"] == "ellipse"
    assert gltf.asset.extras["renderer"] == "exact_ray_evaluation"
    blob = gltf.binary_blob()
    attrs = prim.attributes.__dict__ if not isinstance(prim.attributes, dict) else prim.attributes
    attrs = {**attrs, **getattr(prim.attributes, "_extra", {})} if not isinstance(prim.attributes, dict) else attrs

    def read(name):
        index = attrs.get(name)
        if index is None:  # pygltflib keeps semantics it does not know in the object's extra fields
            index = json.loads(gltf.to_json())["meshes"][0]["primitives"][0]["attributes"][name]
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
        data = np.frombuffer(blob, "<f4", acc.count * width, view.byteOffset + (acc.byteOffset or 0))
        return data.reshape(acc.count, width)

    p = "KHR_gaussian_splatting:"
    assert read("POSITION").shape[0] == N
    np.testing.assert_array_equal(read("POSITION"), splats.means)
    np.testing.assert_allclose(read(p + "SCALE"), np.exp(splats.log_scales.astype(np.float64)), rtol=1e-6)
    xyzw = read(p + "ROTATION")
    assert _same_rotation(xyzw[:, [3, 0, 1, 2]], splats.quats_wxyz, 1e-6)
    np.testing.assert_allclose(read(p + "OPACITY")[:, 0], splats.opacities(), atol=1e-7)
    np.testing.assert_array_equal(read(p + "SH_DEGREE_0_COEF_0"), splats.sh_dc)
    np.testing.assert_array_equal(read(p + "SH_DEGREE_3_COEF_6"), splats.sh_rest[:, 14])


def test_spz_read_by_gsply(splats, tmp_path):
    gsply = pytest.importorskip("gsply")
    write_spz(splats, tmp_path / "s.spz", META)
    data = gsply.read_spz(tmp_path / "s.spz")
    assert len(data.means) == N
    # SPZ's precision: positions 1/4096, log-scales 1/16, rotations 10-bit smallest three, opacity and colour
    # bytes, SH bytes of 1/128
    assert np.abs(data.means - splats.means).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(data.scales - splats.log_scales).max() <= 0.5 / 16 + 1e-5
    assert _same_rotation(np.asarray(data.quats), splats.quats_wxyz, 2e-3)
    opac = 1 / (1 + np.exp(-np.asarray(data.opacities, np.float64)))
    assert np.abs(opac - splats.opacities()).max() <= 0.5 / 255 + 1e-6
    dc_step = 1 / (255 * 0.15)
    inside = np.abs(splats.sh_dc) < 0.5 / 0.15 - dc_step  # colours SPZ's byte can hold
    assert np.abs(np.asarray(data.sh0) - splats.sh_dc)[inside].max() <= 0.5 * dc_step + 1e-5
    rest = np.asarray(data.shN).reshape(N, -1, 3)
    assert np.abs(rest - splats.sh_rest).max() <= 0.5 / 128 + 1e-6
    assert json.loads((tmp_path / "s.spz.json").read_text())["renderer"] == "exact_ray_evaluation"


def test_ewa_cpu_compositing_matches_direct_evaluation():
    """Two isotropic Gaussians on the x axis: the EWA image at a pixel is the 3DGS blend computed by hand from
    the projected 2D Gaussians (covariance s^2 J J^T + 0.3 I, J the projection's Jacobian at the mean)."""
    f, size = 20.0, 16
    view = PinholeView(torch.eye(4, dtype=torch.float64), torch.tensor([[f, 0, 8.0], [0, f, 8.0], [0, 0, 1.0]],
                       dtype=torch.float64), size, size)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 4.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[0.1] * 3, [0.3] * 3], dtype=torch.float64)
    opac = torch.tensor([0.6, 0.9], dtype=torch.float64)
    sh = torch.zeros(2, 1, 3, dtype=torch.float64)
    sh[0, 0, 0], sh[1, 0, 1] = 1.0, 1.0  # red in front, green behind
    image = ewa_image_cpu(means, quats, scales, opac, sh, 0, view)
    u, v = 9.5, 8.5  # pixel (row 8, column 9)
    alphas, colors = [], []
    for m, s, o, c in zip(means, scales, opac, sh[:, 0] * 0.28209479177387814 + 0.5):
        x, y, z = m.tolist()
        var_u = float(s[0]) ** 2 * (f * f / z ** 2 + f * f * x * x / z ** 4) + 0.3  # y = 0: no cross term
        var_v = float(s[0]) ** 2 * f * f / z ** 2 + 0.3
        du, dv = u - (f * x / z + 8.0), v - (f * y / z + 8.0)
        alphas.append(min(0.999, float(o) * math.exp(-0.5 * (du * du / var_u + dv * dv / var_v))))
        colors.append(c)
    expected = alphas[0] * colors[0] + (1 - alphas[0]) * alphas[1] * colors[1]
    assert torch.allclose(image[8, 9], expected, atol=1e-9)


def _one_gaussian_images(mean, quat, scale, opacity, color, f, size):
    """(exact, EWA) [H, W] images of one Gaussian (black background) in numpy float64, from their definitions:
    exact: opacity x exp(-D^2 / 2), D^2 the smallest Mahalanobis distance of the half-line through the pixel
    centre (closed form); EWA: the covariance projected by the Jacobian at the mean, plus 0.3 px^2. Both skip
    alpha < 1/255."""
    w, x, y, z = np.asarray(quat) / np.linalg.norm(quat)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    cov = rot @ np.diag(np.square(scale)) @ rot.T
    prec, mu = np.linalg.inv(cov), np.asarray(mean)
    v, u = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    rays = np.stack([(u - size / 2) / f, (v - size / 2) / f, np.ones_like(u)], -1)
    t = np.maximum((rays @ prec @ mu) / np.einsum("hwi,ij,hwj->hw", rays, prec, rays), 0.0)  # nearest along the ray
    d = t[..., None] * rays - mu
    exact = opacity * np.exp(-0.5 * np.einsum("hwi,ij,hwj->hw", d, prec, d))
    jac = np.array([[f / mu[2], 0, -f * mu[0] / mu[2] ** 2], [0, f / mu[2], -f * mu[1] / mu[2] ** 2]])
    cov2d = jac @ cov @ jac.T + 0.3 * np.eye(2)
    centre = f * mu[:2] / mu[2] + size / 2
    e = np.stack([u, v], -1) - centre
    ewa = opacity * np.exp(-0.5 * np.einsum("hwi,ij,hwj->hw", e, np.linalg.inv(cov2d), e))
    return [np.where(a >= 1 / 255, a, 0.0)[..., None] * np.asarray(color) for a in (exact, ewa)]


def test_ewa_report_is_the_psnr_between_the_exact_and_the_splatted_image():
    """A large Gaussian close to the camera, where EWA's linearisation is visibly off: the report's PSNR is the
    one between the two images computed from their definitions (_one_gaussian_images), to 0.01 dB (24.4 dB
    here: a wrong image on either side moves it by more)."""
    f, size = 12.0, 24
    view = PinholeView(torch.eye(4, dtype=torch.float64), torch.tensor([[f, 0, size / 2], [0, f, size / 2],
                       [0, 0, 1.0]], dtype=torch.float64), size, size)
    mean, quat, scale, opacity = [0.3, 0.0, 1.2], [0.9, 0.1, 0.3, 0.0], [0.6, 0.2, 0.4], 0.8
    report = compare(torch.tensor([mean], dtype=torch.float64), torch.tensor([quat], dtype=torch.float64),
                     torch.tensor([scale], dtype=torch.float64), torch.tensor([opacity], dtype=torch.float64),
                     torch.ones(1, 1, 3, dtype=torch.float64), 0, [view])
    color = [0.28209479177387814 + 0.5] * 3  # SH band 0 of 1.0, plus 0.5
    exact, ewa = _one_gaussian_images(mean, quat, scale, opacity, color, f, size)
    expected = -10 * math.log10(float(np.mean((np.clip(exact, 0, 1) - np.clip(ewa, 0, 1)) ** 2)))
    assert len(report.psnr_db) == 1 and report.psnr_db[0] == pytest.approx(expected, abs=0.01)
    assert f"{expected:.2f} dB" in report.line()


def test_export_command_on_a_checkpoint(tmp_path, capsys):
    """A two-step run on three room frames, exported by the command's own function: every format holds the
    trained count of Gaussians, and the EWA-vs-exact figure is printed and recorded."""
    from conftest import copy_room, tiny_trainer_config, train_in_process
    from geer_ns.export.cli import ExportConfig, export

    config = tiny_trainer_config(copy_room(tmp_path / "data", 3), tmp_path / "out", "room", 2)
    config.save_config()
    checkpoint = train_in_process(config)
    trained = torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]["_model.gauss_params.means"]
    meta = export(ExportConfig(config.get_base_dir() / "config.yml", tmp_path / "export", ewa_views=1, ewa_size=16))
    assert "EWA splatting vs geer's exact rendering" in capsys.readouterr().out
    assert meta["gaussians"] == trained.shape[0] and math.isfinite(meta["ewa_vs_exact_psnr_db"])
    gsply = pytest.importorskip("gsply")
    pygltflib = pytest.importorskip("pygltflib")
    assert len(gsply.read_spz(tmp_path / "export" / "splat.spz").means) == trained.shape[0]
    gltf = pygltflib.GLTF2().load(str(tmp_path / "export" / "splat.glb"))
    assert gltf.accessors[0].count == trained.shape[0]
    assert gltf.asset.extras["ewa_vs_exact_psnr_db"] == meta["ewa_vs_exact_psnr_db"]


def test_mixed_degrees_store_the_highest_kept(splats, tmp_path):
    """Per-Gaussian degrees (geer_ns/sh_degrees): each file stores the highest degree kept, lower-degree Gaussians'
    higher coefficients as the zeros they are; the files are smaller than at full degree."""
    from dataclasses import replace

    from plyfile import PlyData

    degrees = np.random.default_rng(1).integers(0, 2, N).astype(np.uint8)  # 0 and 1 only
    rest = splats.sh_rest.copy()
    for i, d in enumerate(degrees):
        rest[i, (d + 1) ** 2 - 1:] = 0.0
    mixed = replace(splats, sh_rest=rest, sh_degrees=degrees)
    assert mixed.sh_degree == 1
    sizes = {}
    for name, writer, full in (("ply", write_ply, splats), ("spz", write_spz, splats), ("glb", write_glb, splats)):
        writer(mixed, tmp_path / f"m.{name}", META)
        writer(full, tmp_path / f"f.{name}", META)
        sizes[name] = (tmp_path / f"m.{name}").stat().st_size / (tmp_path / f"f.{name}").stat().st_size
    v = PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    names = [p.name for p in v.properties if p.name.startswith("f_rest_")]
    assert len(names) == 9
    back = np.stack([v[n] for n in names], 1).reshape(N, 3, 3).transpose(0, 2, 1)
    np.testing.assert_array_equal(back, rest[:, :3])
    assert sizes["ply"] < 0.5 and sizes["glb"] < 0.5 and sizes["spz"] < 0.7, sizes
    with gzip.open(tmp_path / "m.spz", "rb") as f:
        assert f.read(16)[12] == 1  # SPZ header: SH degree
