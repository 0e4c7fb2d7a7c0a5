"""The engines and the model meet only through geer_ns/distributed/engine.py: each engine offers every member of
`Engine`, GeerModel every member of `EngineModel`, and no module but the model's own reaches into the model's
private members (`model._x`); the engine's state lives on the engine, the model reads it."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

from geer_ns.distributed.engine import Engine, EngineModel, EngineState
from geer_ns.distributed.gaussian_parallel import GaussianParallel
from geer_ns.distributed.image_parallel import ImageParallel
from geer_ns.model import GeerModel, GeerModelConfig

ROOT = Path(__file__).resolve().parents[1]


def _members(protocol) -> set:
    """The names a Protocol declares: its methods and its annotated attributes."""
    own = {name for name, _ in inspect.getmembers(protocol, inspect.isfunction) if not name.startswith("_")}
    return own | set(protocol.__annotations__)


def test_each_engine_offers_what_the_trainer_asks():
    for engine in (ImageParallel, GaussianParallel):
        methods = {name for name in _members(Engine) if callable(getattr(Engine, name, None))}
        assert methods and all(callable(getattr(engine, name, None)) for name in methods), engine
        assert isinstance(engine.name, str)


def test_the_model_offers_what_engines_use():
    missing = [name for name in _members(EngineModel) if not hasattr(GeerModel, name)
               and name not in ("config", "gauss_params", "strategy", "strategy_state", "camera_optimizer", "views",
                                "training")]  # set in populate_modules / nn.Module.__init__
    assert not missing, missing


def test_no_module_reaches_into_the_models_private_members():
    found = []
    for path in sorted((ROOT / "geer_ns").rglob("*.py")):
        if path.name == "model.py" and path.parent.name == "geer_ns":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\bmodel\._[a-z]", line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, found


def test_engine_state_is_the_engines_and_the_model_only_reads_it():
    """scene_gaussians / images_per_step are read-only on the model (its engine's state), and the config has no
    hidden field for the batch any more."""
    assert not hasattr(GeerModelConfig(), "images_per_step_total")
    for name in ("scene_gaussians", "images_per_step"):
        prop = inspect.getattr_static(GeerModel, name)
        assert isinstance(prop, property) and prop.fset is None, name
    assert EngineState() == EngineState(images_per_step=1, scene_gaussians=None, display_gaussians=None)
