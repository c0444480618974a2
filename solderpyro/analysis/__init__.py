"""Studies of the model itself: the sensitivity of the outputs to the constants."""
