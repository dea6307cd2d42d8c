"""The papers' formulas, transcribed verbatim, for comparison only.

:mod:`sonar_ring.reference.browne` (Browne 2011: eqs 4, 8, 9-19, 26 and the
Appendix A edge solution) and :mod:`sonar_ring.reference.barshan_kuc` (Barshan &
Kuc 1990: eqs 15-23 and 41) are the baseline that the production path,
:mod:`sonar_ring.localise`, is tested and benchmarked against.  Nodes never call
them: they keep the papers' conditioning (and, where noted, their typos' fixes),
not the package's numerics or input checks.
"""
