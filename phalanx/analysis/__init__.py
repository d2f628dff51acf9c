"""What a run means: the paper's error metrics, the figures, the results folder, and the
report (`phalanx report`, docs/RESULTS.md).
"""
