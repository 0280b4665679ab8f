"""The bench's library steps: measurements as functions of a sequence, a config and counts, that print progress but
read no command line and write no report (the study modules in :mod:`twohr_lab.bench` do that)."""
