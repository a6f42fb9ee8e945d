"""Next-best-view planning (DESIGN.md section 3.8): candidate views and their utility
(:mod:`.nbv`), and the closed-loop active scan that compares planners (:mod:`.scan`)."""
