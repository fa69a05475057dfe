"""Reproductions of the papers' experiments on synthetic worlds.

Each module is a script (``python bench/paper/<name>.py --help``) that writes
``bench/results/paper/<name>.md`` with the paper's numbers beside ours, the raw figures as
``<name>.json`` and a PNG plot:

* :mod:`.weiss_table1` -- Weiss et al. 2008, Table I (errors of global, SIFT and hybrid
  localisation for every train/test illumination) and the error curves of Fig. 4 a-d;
* :mod:`.weiss_table2` -- Table II (share of SIFT steps, time per frame, speed-up), from
  the Table I run;
* :mod:`.weiss_fig4` -- Fig. 4 e (particle count) and f (switching thresholds);
* :mod:`.flyphone_fig7` -- Erhard et al. (Flyphone) Fig. 7 and Fig. 9, retrieval error of
  every global feature under every similarity measure, same and changed illumination.

Worlds are generated once and cached under ``bench/.cache/``.
"""
