"""Evaluation: image metrics, the tactile classification task, aggregation over seeds and the report."""
