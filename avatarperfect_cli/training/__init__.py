"""Building blocks of avatar training: losses, metrics, optimizers, densification, the loop."""
