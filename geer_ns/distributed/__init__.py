"""Training on one or many processes and machines through torch.distributed: one layer of its own.

    world               the process group and the few collectives used (bucketed all-reduce, gathers, broadcasts)
    schedule            the effective batch (processes x images per step) and its rule for steps and Adam
    consistency         the start-up check that every process agrees, rank 0's state broadcast, replica checksums
    reductions          each step's gradient and densification-statistics reductions (both engines)
    engine              what an engine and the model offer each other (Engine, EngineModel, EngineState)
    image_parallel      the engine of image-parallel training: identical replicas
    sharded_render      a camera rendered from the rows of every shard it sees (a differentiable all-to-all)
    gaussian_parallel   the engine of Gaussian-parallel training: a shard per process, the scene-wide budget
    streamed_checkpoint one checkpoint file written shard by shard, nothing gathered on one device
    launch              nerfstudio's launcher routed to a worker without its CUDA-only asserts (geer runs only)

The training step that drives an engine is geer_ns.training.trainer.

The processes are started by nerfstudio's launcher (`ns-train geer --machine.num-devices N`, with
`--machine.num-machines M --machine.machine-rank r --machine.dist-url tcp://HOST:PORT` across machines).
"""
