"""geer-export: a trained geer scene as the standard 3DGS PLY, glTF KHR_gaussian_splatting (.glb) and SPZ, with
how far a standard EWA viewer's image will be from geer's (docs/export.md)."""

from .formats import WRITERS, Splats, write_glb, write_ply, write_spz

__all__ = ["Splats", "WRITERS", "write_glb", "write_ply", "write_spz"]
