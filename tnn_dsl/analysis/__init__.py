"""tnn_dsl.analysis."""
