"""Running things: training, evaluation, experiments, the stress suite, the benchmark."""
