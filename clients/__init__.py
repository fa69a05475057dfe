"""vloc clients: the Python SDK, the ``vloc`` command line, device simulators and the
synthetic world generator."""
