"""Evaluation: vision-tracker accuracy, filter consistency statistics, vision figures and performance benchmarks."""
