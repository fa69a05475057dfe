"""Single-image localisation: one image, no session, answered synchronously by one step
of a fresh particle filter in a worker (:mod:`vloc.app.tasks.localize`)."""
