"""Evaluation metrics: success, cost distances (EPIC), hull behaviour."""
