"""The apps layer: what a user runs on top of the algorithms. :mod:`~pe_rlhf.apps.cli` (the ``pe-rlhf`` command),
:mod:`~pe_rlhf.apps.sweeps` (``pe-rlhf sweep``: a grid of recipe runs as Ray tasks) and :mod:`~pe_rlhf.apps.compare`
(``pe-rlhf compare``: tables and curves from finished runs). Nothing below this layer imports it.
"""
