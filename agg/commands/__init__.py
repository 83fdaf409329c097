"""Sub-commands of the ``agg`` console script, one module each (see ``agg.cli``).

Command modules import their heavy dependencies inside ``run`` so that ``agg --help`` stays fast.
"""
