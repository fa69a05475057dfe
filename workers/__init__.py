"""vloc workers: the localisation core library and the engines that run it."""
