"""The service's code that the engine runs in its worker processes, and no other.

The engine runs a task by a pickled reference to its function, so whatever a task imports is
imported in every worker: the tasks read and write the database through their own
connections and call the core, and import no FastAPI and no router (``tests/test_layers.py``
checks both). :func:`vloc.app.engine.run_task` runs the functions of this package and refuses
any other.

- :mod:`.build`: a map's build, image by image, then the packing of a revision;
- :mod:`.teach`: a taught route's build;
- :mod:`.localize`: one image localised against a packed revision;
- :mod:`.images`: an upload decoded in full, to check it.
"""
