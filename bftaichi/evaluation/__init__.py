"""Judging a reconstruction: geometry and uncertainty metrics against ground truth
(:mod:`.metrics`) and held-out real views (:mod:`.evalviews`)."""
