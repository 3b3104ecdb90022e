"""Scan planning for a catalogue of parts (``flyscan plan``): for each part, every candidate
grasp, pass direction (a turn about z_T) and pass preset is scanned in the simulated cell as a
task on Dask distributed, judged by its pose's information, ranked, and written as the part's
``plan.json`` with a catalogue summary (docs/planning.md).

Modules: the candidates (``planning.candidates``), one candidate's scan and verdict
(``planning.evaluate``), the catalogue folder and the result cache (``planning.catalogue``,
``planning.cache``), the run on a cluster (``planning.run``), the ranking and the files
written (``planning.report``). It sits above the simulator and below the service's command
line; ``flyscan scan`` and the service read a plan through ``scanner_core.scanplan`` only.
"""
