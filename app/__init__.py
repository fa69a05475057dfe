"""The vloc web service: HTTP and WebSocket I/O, auth and persistence.

Nothing in this package runs numerics: routes validate, authorise and enqueue; the engine in
:mod:`workers.engine` runs the core library in worker processes.
"""
