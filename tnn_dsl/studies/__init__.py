"""tnn_dsl.studies."""
