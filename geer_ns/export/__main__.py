from geer_ns.export.cli import entrypoint

entrypoint()
