"""Judging estimates: metrics against ground truth, the replay report, the speed and memory bench."""
