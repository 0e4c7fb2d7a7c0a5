"""geer-compare: geer against splatfacto's variants on one capture (docs/compare.md).

Modules: ``ewa_tiles`` / ``ewa_cpu`` (gsplat's classic EWA rasterization in PyTorch, for machines without CUDA),
``splatfacto`` (splatfacto's model with the host work-arounds scoped to these runs), ``resample`` and ``capture``
(test views; the capture seen by another camera), ``methods``, ``run`` (train, render, score), ``report`` and
``cli``.
"""
