"""Measuring the localisers, apart from the algorithms they measure: data sets of geotagged
images (:mod:`.datasets`), an experiment built from one (:mod:`.experiment`), photometric
variants of its query frames (:mod:`.photometric`), the offline evaluation protocol of Weiss
et al. 2008, section V (:mod:`.evaluate`) and its tables and plots (:mod:`.report`).

The service never imports this package; ``vloc eval``, the benchmarks and the paper
experiments do.
"""
