"""Demonstrations: datasets, ROS bag ingestion, synthetic Odin-like bags, system identification."""
