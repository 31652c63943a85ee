"""Datasets: the format defined once, the generator, statistics, simulator captures, readers
and torch datasets."""
