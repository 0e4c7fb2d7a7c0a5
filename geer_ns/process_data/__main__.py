from geer_ns.process_data.cli import entrypoint

entrypoint()
