"""Which SH bands each Gaussian keeps: the ones its training images show, chosen once, by measurement.

At the run's last step (`last_step`: the scene as it will be kept) every training view is rendered once with its
colors as a leaf. The gradient of the sum of the view's supervised pixels w.r.t. Gaussian i's color is W_iv, the
sum of its blend weights over the view's pixels. Keeping degree d, with its bands up to d refit to the colours the
views saw (refit.py), changes its color in view v by Delta_iv(d) = Y_d(u_iv) c'_i,d - f_iv (f_iv: its every-band
color along its view direction u_iv), and pixel p by sum_i w_ip Delta_iv; as sum_i w_ip <= 1,
|sum_i w_ip Delta_iv|^2 <= sum_i w_ip |Delta_iv|^2 (Cauchy-Schwarz), so the squared error the images gain is at
most sum_i e_i(d_i), e_i(d) = sum_v W_iv |Delta_iv(d)|^2 (to first order: at a trained optimum the cross term with
the residual vanishes). Gaussian i's score at degree d is the weighted RMS color change
r_i(d) = sqrt(e_i(d) / sum_v W_iv); at a threshold tau it keeps the least d with r_i(d) <= tau. A Gaussian no
training view blends keeps degree 0.

The threshold is measured, not assumed: rendering every training view with the candidate degrees gives their
PSNR loss against all bands, and the choice takes the largest tau (a half-octave ladder) whose loss stays within
`budget_db`. Before that, the highest degree any Gaussian keeps is capped at the least degree at which every
Gaussian's loss stays within the budget: the fixed-layout formats (PLY, SPZ, glTF) store every Gaussian at the
highest degree, so the cap sets their size, and it is given the budget first.
The kept coefficients take their refit values, the dropped ones are set to zero with their Adam moments; the
kernels neither read nor differentiate them (csrc/geer_math.h gaussian_sh_degree), so they stay zero. Why this
schedule and the measurements: docs/training.md, benchmarks/skip_unneeded.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import torch
from torch import Tensor

from geer_ns.distributed.world import all_reduce_, current_world
from geer_ns.render import render
from geer_ns.render.cull import view_rows
from geer_ns.render.sh import sh_band_colors
from geer_ns.render.transforms import camera_offsets
from geer_ns.sh_degrees.packing import DEGREES, kept
from geer_ns.sh_degrees.refit import FIT_DEGREE, SeenColours, basis_up_to_fit, refit
from geer_ns.shutter_views import model_view

LADDER = [0.5 * 2.0 ** (-j / 2) for j in range(21)]  # thresholds tau, colors in [0, 1]: 0.5 down to 5e-4


def last_step(trainer) -> int:
    """The step a nerfstudio run ends at, where the bands are chosen: its loop runs --max-num-iterations steps from
    its start step (`_start_step`, nerfstudio 1.1.5's name: a resumed run's checkpoint step + 1).

    Why the end and not the end of densification: the bands a trained scene's colours need and the bands its
    training needs differ. On the dev room the final Gaussians, refit at degree 1, lose 0.02 dB, but the same scene
    kept at degree <= 1 from the end of densification on ends 0.2 dB lower (benchmarks/skip_unneeded.md)."""
    return trainer._start_step + trainer.config.max_num_iterations - 1


@dataclass
class BandErrors:
    """What one pass over the training views measured (summed over processes)."""

    errors: Tensor  # [N, B] float64: e_i(d) for d = 0 .. B-1 (module docstring); column B-1 is 0
    weights: Tensor  # [N] float64: sum_v W_iv
    fits: List[Tensor]  # [N, (d + 1)^2, 3] each Gaussian's refit coefficients at degree d, for d = 0 .. B-2
    squared: float  # the views' squared error with every band
    count: float  # the values it sums over


def _views(pipeline) -> List[int]:
    """This process's share of the training images."""
    world = current_world()
    return list(range(len(pipeline.datamanager.cached_train)))[world.rank :: world.size]


def _render_view(model, camera, colors_of: Callable[[Tensor, Tensor, Tensor], Tensor]):
    """One training view of the model's Gaussians (the rows it can see), colored by colors_of(rows, bands, basis),
    bands [K, B, 3] each band's part of each row's color, basis [K, refit.FIT_BASES] the SH basis at the rows' view
    directions. Returns (render output, view, background, rows, bands, basis)."""
    view = model.view_for(camera)
    params = {name: p.detach() for name, p in model.render_gaussians().items()}
    means = params["means"]
    grid = view.rays.to(means.device)
    viewmat, motion = model_view(model, camera, view.rays, means.device)  # a rolling shutter as captured
    rows = torch.arange(len(means), device=means.device) if motion is not None else view_rows(
        means, torch.exp(params["scales"].amax(-1)), torch.sigmoid(params["opacities"]).reshape(-1), viewmat, grid,
        model.config.lambda_mode)
    part = {name: p[rows] for name, p in params.items()}
    scales, opacities = model.activated(part)
    coeffs, _ = model.colors(part)
    degree = int(math.isqrt(coeffs.shape[1]) - 1)
    directions = camera_offsets(part["means"], viewmat)
    bands, basis = sh_band_colors(coeffs, directions, degree), basis_up_to_fit(directions)
    background = model.render_background().to(means)
    out = render(part["means"], part["quats"], scales, opacities, colors_of(rows, bands, basis), viewmat, grid,
                 background=background, lambda_mode=model.config.lambda_mode, backend=model.config.renderer_backend,
                 max_pairs=model.config.max_pairs, motion=motion)
    return out, view, background, rows, bands, basis


def _squared_error(model, out, view, background, camera, batch) -> Tuple[Tensor, Tensor, Tensor]:
    """(valid [H, W, 1], squared error sum, values summed) of a rendered training view against its image."""
    outputs = model.view_outputs(out, view, background, camera)
    valid = model.supervised_mask(outputs, batch)
    gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
    squared = torch.where(valid, (outputs["rgb"].detach() - gt) ** 2, 0.0).double().sum()
    return valid, squared, valid.sum().double() * gt.shape[-1]


def _color(rows: Tensor, bands: Tensor, basis: Tensor, degrees: Optional[Tensor], fits: List[Tensor]) -> Tensor:
    """[K, 3] the color of each row at its degree (None: every band): every band's sum at the highest, its refit
    coefficients (fits[d] [N, (d + 1)^2, 3]) below; as sh_to_color, +0.5 and floored at 0."""
    color = bands.sum(1)
    if degrees is not None:
        own = degrees[rows].long()
        for d, fit in enumerate(fits):
            at = own == d
            n = (d + 1) ** 2
            color = torch.where(at[:, None], torch.einsum("kb,kbc->kc", basis[:, :n], fit[rows, :n]), color)
    return (color + 0.5).clamp_min(0.0)


def band_errors(model, pipeline) -> BandErrors:
    """The pass with every band (module docstring): each Gaussian's e_i(d) with its refit coefficients, its
    weight, and the views' error."""
    n = model.num_points
    coeffs = model.colors(model.render_gaussians())[0].detach()
    bands_count = int(math.isqrt(coeffs.shape[1]))
    seen = SeenColours.zeros(n, model.device)
    weights = torch.zeros(n, dtype=torch.float64, device=model.device)
    totals = torch.zeros(2, dtype=torch.float64, device=model.device)
    for index in _views(pipeline):
        camera, batch = pipeline.datamanager.train_view(index)
        leaves = {}

        def colors_of(rows, bands, basis):
            leaves["rgb"] = _color(rows, bands, basis, None, []).detach().requires_grad_(True)
            return leaves["rgb"]

        with torch.enable_grad():
            out, view, background, rows, bands, basis = _render_view(model, camera, colors_of)
            valid, squared, count = _squared_error(model, out, view, background, camera, batch)
            (out.rgb * valid).sum().backward()
        w = leaves["rgb"].grad.double().mean(-1)  # the same on each channel
        seen.add(rows, w, basis, bands.sum(1))
        weights.index_add_(0, rows, w)
        totals += torch.stack([squared, count])
    all_reduce_([*seen.tensors(), weights, totals])
    errors = torch.zeros(n, bands_count, dtype=torch.float64, device=model.device)
    fits = []
    for d in range(min(bands_count - 1, FIT_DEGREE + 1)):
        fit, errors[:, d] = refit(seen, coeffs, d)
        fits.append(fit)
    return BandErrors(errors, weights, fits, float(totals[0]), float(totals[1]))


@torch.no_grad()
def measured_loss_db(model, pipeline, degrees: Tensor, reference: BandErrors) -> float:
    """The training views' PSNR loss (dB) of rendering each Gaussian at `degrees` instead of every band."""
    totals = torch.zeros(2, dtype=torch.float64, device=model.device)
    for index in _views(pipeline):
        camera, batch = pipeline.datamanager.train_view(index)
        out, view, background, *_ = _render_view(
            model, camera, lambda rows, bands, basis: _color(rows, bands, basis, degrees, reference.fits))
        _, squared, count = _squared_error(model, out, view, background, camera, batch)
        totals += torch.stack([squared, count])
    all_reduce_([totals])
    mse, full = float(totals[0] / totals[1].clamp_min(1)), reference.squared / max(reference.count, 1.0)
    return 10.0 * math.log10(max(mse, 1e-20) / max(full, 1e-20))


def degrees_at(scores: Tensor, tau: float, cap: int) -> Tensor:
    """[N] the least degree d <= cap whose score r_i(d) <= tau (cap where none is)."""
    fits = scores[:, : cap + 1] <= tau
    fits[:, cap] = True
    return fits.int().argmax(1)


@dataclass
class Choice:
    degrees: Tensor  # [N] uint8
    cap: int  # the highest degree any Gaussian keeps
    tau: float  # the threshold (0: every band up to the cap)
    loss_db: float  # the training views' measured PSNR loss at the choice
    probes: int  # the measuring passes it took
    fits: List[Tensor]  # BandErrors.fits: the coefficients a Gaussian at degree d < the highest keeps


def choose(model, pipeline, budget_db: float) -> Choice:
    """Each Gaussian's degree (module docstring): the cap first, within the budget, then the threshold."""
    errors = band_errors(model, pipeline)
    top = errors.errors.shape[1] - 1
    scores = (errors.errors / errors.weights.clamp_min(1e-300)[:, None]).sqrt()
    scores[errors.weights <= 0] = 0.0
    probes, losses = 0, {}

    def loss(degrees: Tensor) -> float:
        nonlocal probes
        probes += 1
        return measured_loss_db(model, pipeline, degrees, errors)

    cap = top
    for candidate in range(top):
        losses[candidate] = loss(torch.full_like(errors.weights, candidate, dtype=torch.long))
        if losses[candidate] <= budget_db:
            cap = candidate
            break
    best, best_loss = degrees_at(scores, 0.0, cap), losses.get(cap, 0.0)
    lo, hi = 0, len(LADDER)  # LADDER[j] for j >= hi is known to pass (hi = len: none tested yet)
    tau = 0.0
    while lo < hi:
        mid = (lo + hi) // 2
        candidate = degrees_at(scores, LADDER[mid], cap)
        measured = loss(candidate)
        if measured <= budget_db:
            hi, best, best_loss, tau = mid, candidate, measured, LADDER[mid]
        else:
            lo = mid + 1
    return Choice(best.to(torch.uint8), cap, tau, best_loss, probes, errors.fits)


@torch.no_grad()
def set_degrees(model, degrees: Tensor, fits: Optional[List[Tensor]] = None) -> Tensor:
    """Each Gaussian's coefficients at its degree: a Gaussian at degree d < len(fits) takes its refit coefficients
    fits[d] [N, (d + 1)^2, 3] (BandErrors.fits; None: its own, cut off), its dropped ones zero; the degrees in the
    strategy state (densification carries them with the rows). Returns the dropped entries of features_rest."""
    rest, dc = model.gauss_params["features_rest"], model.gauss_params["features_dc"]
    degrees = degrees.to(rest.device)
    for d, fit in enumerate(fits or []):
        at = degrees.long() == d
        dc.data[at] = fit[at, 0].to(dc.dtype)
        rest.data[at, : (d + 1) ** 2 - 1] = fit[at, 1:].to(rest.dtype)
    dropped = ~kept(degrees, rest.shape[1])
    rest.data[dropped] = 0.0
    model.strategy_state[DEGREES] = degrees.to(dtype=torch.uint8)
    return dropped


@torch.no_grad()
def keep_degrees(model, optimizers, degrees: Tensor, fits: Optional[List[Tensor]] = None) -> None:
    """Give each Gaussian its degree (set_degrees), the Adam moments of its dropped coefficients set to zero."""
    rest = model.gauss_params["features_rest"]
    dropped = set_degrees(model, degrees, fits)
    for value in optimizers["features_rest"].state.get(rest, {}).values():
        if isinstance(value, Tensor) and value.shape == rest.shape:
            value[dropped] = 0.0


def highest_band_trained(step: int, sh_degree: int, sh_degree_interval: int) -> bool:
    """Whether the SH schedule's highest band has trained for one interval by `step`: before, the degrees are not
    chosen (a run resumed for more steps still gains its bands)."""
    return step >= (sh_degree + 1) * sh_degree_interval


class BandChoice:
    """Training callback (after each iteration): at the trainer's last step (`last_step`, read when called: a
    resumed run's start is known only once its checkpoint is loaded), choose and keep each Gaussian's degree, once
    the highest band has trained (highest_band_trained); `say` gets one line. A run whose degrees were chosen
    (resumed after its end) keeps them."""

    def __init__(self, pipeline, optimizers, trainer, budget_db: float, say: Callable[[str], None]):
        self.pipeline, self.optimizers, self.trainer, self.budget_db, self.say = (pipeline, optimizers, trainer,
                                                                                  budget_db, say)

    def __call__(self, step: int) -> None:
        model = self.pipeline.model
        if step != last_step(self.trainer) or DEGREES in model.strategy_state:
            return
        degree, interval = model.config.sh_degree, model.config.sh_degree_interval
        if not highest_band_trained(step, degree, interval):
            self.say(f"geer: step {step}: every SH band kept (degree {degree} is reached at step "
                     f"{degree * interval} and trained to {(degree + 1) * interval}; the degrees are chosen at the "
                     "last step of a run that gets there)")
            return
        choice = choose(model, self.pipeline, self.budget_db)
        keep_degrees(model, self.optimizers.optimizers, choice.degrees, choice.fits)
        counts = torch.bincount(choice.degrees.long(), minlength=4).tolist()
        share = ", ".join(f"{100.0 * c / max(len(choice.degrees), 1):.1f} % at {d}" for d, c in enumerate(counts))
        self.say(f"geer: step {step}: SH degree per Gaussian chosen ({share}; at most {choice.cap}; training views "
                 f"{choice.loss_db:+.3f} dB against every band, budget {self.budget_db} dB, {choice.probes} "
                 "measuring passes)")
