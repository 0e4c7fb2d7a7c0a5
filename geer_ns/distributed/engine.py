"""What a training engine and the model it trains offer each other.

An engine (image_parallel.ImageParallel, gaussian_parallel.GaussianParallel) shares a step's images and the
scene's Gaussians out over the processes; geer_ns.training.trainer drives it through `Engine`. The engine
uses only the model's public side, `EngineModel` (GeerModel's); the model reads only the engine's
`EngineState`, which the engine writes and attaches to the model (GeerModel.attach). A model no engine trains
(ns-eval, ns-render, the viewer of a finished run, tests) keeps the default EngineState: one image per step,
every Gaussian held here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Protocol, Tuple

import torch
from torch import Tensor


@dataclass
class EngineState:
    """What an engine shares with the model it trains: written by the engine, read by the model."""

    images_per_step: int = 1
    """Images one training step sees over every process (the effective batch). The model's step-valued options
    count steps of that many images; checkpoints record it so that steps convert on resume."""
    scene_gaussians: Optional[int] = None
    """Gaussians over every shard where this process holds one shard (Gaussian-parallel), else None."""
    display_gaussians: Optional[Dict[str, Tensor]] = None
    """What evaluation and the viewer render in place of the model's own parameters (gathered shards), if set."""


class Engine(Protocol):
    """What geer_ns.training.trainer asks of an engine (`--pipeline.model.distributed` picks it)."""

    name: str
    state: EngineState

    def start(self) -> None:
        """After the model, optimizers and any checkpoint are loaded: agree with the other processes."""

    def describe(self) -> List[str]:
        """Start-up lines (rank 0 says them)."""

    def views(self, step: int) -> Iterator[Tuple[Dict[str, Tensor], Callable[[], Dict[str, Tensor]]]]:
        """This process's images of the step: (batch, a function rendering its outputs), one at a time."""

    def reduce_gradients(self) -> None:
        """After every image's backward: the step's gradients, reduced over the processes and averaged."""

    def reduce_statistics(self, model: "EngineModel") -> None:
        """The step's densification statistics over every process, handed to model.use_step_statistics."""

    def step_rows(self, model: "EngineModel") -> Tensor:
        """The rows of this process's Gaussians the step's views (over every process) could see, ascending: the
        rows a selective optimizer steps (geer_ns/optim/selective_adam.py)."""

    def callbacks(self) -> List[Any]:
        """nerfstudio TrainingCallbacks to run after the model's own."""

    def write_checkpoint(self, step: int, path: Path) -> bool:
        """The run's checkpoint at `path` (a collective where the engine needs one); True where written."""

    def evaluate(self, step: int, run: Callable[[], None]) -> None:
        """nerfstudio's evaluation (`run`) on rank 0, the others helping where the engine needs them."""


class EngineModel(Protocol):
    """What an engine uses of the model it trains (geer_ns.model.GeerModel): public members only."""

    config: Any  # GeerModelConfig
    gauss_params: torch.nn.ParameterDict
    strategy: Any
    strategy_state: Dict[str, Any]
    views: List[Any]  # this step's densification records (densify.signal.ViewRecord), the engine may add
    training: bool
    num_points: int
    device: torch.device
    needs_step_statistics: bool

    def attach(self, state: EngineState) -> None:
        """Be trained by the engine whose state this is (before any checkpoint is loaded)."""

    def view_for(self, camera: Any) -> Any:
        """The ray grid (data.views BeapView / NativeView) a nerfstudio camera is rendered on."""

    def render_gaussians(self) -> Optional[Dict[str, Tensor]]:
        """The parameters a render uses (cropped, or the engine's display copy); None if none is left."""

    def render_background(self) -> Tensor:
        """The background color a render composites over now (one random color per training step)."""

    def colors(self, params: Dict[str, Tensor]) -> Tuple[Tensor, Optional[int]]:
        """The renderer's colors of `params` and the SH degree in use (None: plain RGB)."""

    def activated(self, params: Dict[str, Tensor]) -> Tuple[Tensor, Tensor]:
        """(scales, opacities) as the renderer takes them."""

    def render_options(self) -> Dict[str, Any]:
        """The renderer options (backend, lambda_mode, max_pairs) every render of the model passes."""

    def render_pose(self, camera: Any) -> Tensor:
        """The camera-to-world a render of a nerfstudio camera uses (a training camera's refined pose while
        training; otherwise the given pose, in the scene's frame)."""

    def viewmat(self, camera_to_world: Tensor, device: Any) -> Tensor:
        """The world-to-camera matrix (OpenCV axes, float64) of a nerfstudio pose."""

    def probe(self, view: Any, means: Tensor, viewmat: Tensor, scales: Tensor, opacities: Tensor,
              rows: Optional[Tensor] = None) -> Any:
        """The densification leaves (densify.signal.ViewProbe) of a training view of these Gaussians (the
        model's `rows`, or all of them)."""

    def view_outputs(self, out: Any, view: Any, background: Tensor, camera: Any,
                     normals: Any = None) -> Dict[str, Tensor]:
        """nerfstudio's outputs of a render of `camera`."""

    def step_statistics(self) -> Any:
        """This process's densification statistics of the step so far."""

    def use_step_statistics(self, statistics: Any) -> None:
        """The step's statistics over every process, for the densification after the step."""

    def step_rows(self) -> Tensor:
        """[N] bool: the Gaussians held here that this process's views of the step could see."""

    def get_outputs(self, camera: Any) -> Dict[str, Tensor]:
        """nerfstudio's render of one camera."""

    def get_outputs_for_camera(self, camera: Any, obb_box: Any = None) -> Dict[str, Tensor]:
        """nerfstudio's render of one camera for evaluation and the viewer."""
