"""The compiled renderer checked against the PyTorch renderer where it runs: the self-test suite (suite.py,
scenes.py) that geer_ns/render/verdict.py runs in a child process (child.py), and the training sentinel
(sentinel.py). docs/cuda.md."""
