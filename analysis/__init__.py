"""Analysis of MARCH run directories (files only: pandas, numpy, matplotlib, omegaconf).

``python analysis/figures.py <sweep dir>`` is the entry point; the modules split it by job:
``rundirs`` finds and loads runs, ``aggregate`` turns rows into curves and tables, ``plotting``
draws the figures, ``reports`` writes the tables and the stdout summary.
"""
