"""The localisation core: a pure numerical library (numpy, OpenCV, SciPy).

Nothing here imports the web layer, the database or settings; everything works on arrays
and is testable in isolation.
"""
