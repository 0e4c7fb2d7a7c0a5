"""Training on one or many processes and machines through torch.distributed: one layer of its own.

    world       the process group and the few collectives used (bucketed all-reduce, gathers, broadcasts)
    schedule    the effective batch (processes x images per step) and its rule for steps and Adam
    replicas    image-parallel training: identical replicas, reduced gradients and densification statistics
    sharded     Gaussian-parallel training (shards: the sharded render; streamed_checkpoint: its checkpoints)
    trainer     the training step (nerfstudio's Trainer with images per step, the reductions, rank-0 duties)

The processes are started by nerfstudio's launcher (`ns-train geer --machine.num-devices N`, with
`--machine.num-machines M --machine.machine-rank r --machine.dist-url tcp://HOST:PORT` across machines);
geer_ns.host_fixes makes it work on CPU machines (gloo) and reports a failed process in one line.
"""
