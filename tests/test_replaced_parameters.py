"""After densification replaced the Parameters, nerfstudio's Optimizers.parameters (what clip_grad_norm reads)
holds what the optimizers step, not the replaced tensors (which it would keep alive: a whole seed model)."""

from __future__ import annotations

import weakref

import distributed_harness as harness
from conftest import copy_room


def test_optimizers_forget_the_parameters_densification_replaced(tmp_path):
    room = copy_room(tmp_path / "data", 6, n_eval=1)
    config = harness.scenario_config(room, tmp_path, "replaced", steps=8)
    config.machine.device_type = "cpu"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    seed = {name: weakref.ref(p) for name, p in model.gauss_params.items()}
    before = model.num_points
    trainer.train()
    assert model.num_points != before  # densification replaced every Parameter
    for name, p in model.gauss_params.items():
        assert len(trainer.optimizers.parameters[name]) == 1 and trainer.optimizers.parameters[name][0] is p
        assert seed[name]() is None, name  # the seed model's tensor is gone
