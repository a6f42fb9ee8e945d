"""Frame sources: recorded dataset formats and synthetic scenes rendered with ground truth."""
