"""The training loop: nerfstudio's Trainer with a step made of images and an engine (trainer), on one process or
many (the engines and collectives live in geer_ns.distributed)."""
