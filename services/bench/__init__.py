"""``trackgraph bench run``: the paper's tables (segmentation, retrieval, efficiency, the tracker
and gallery ablations) for one sequence and one or more configs, as markdown, JSON and plots.

- :mod:`services.bench.runs`: config variants, mapping runs in their own processes, evaluations;
- :mod:`services.bench.rate`: the highest input rate the distributed system sustains without
  dropping a frame;
- :mod:`services.bench.report`: the tables, the JSON and the plots;
- :mod:`services.bench.core`: the whole bench, step by step.
"""
