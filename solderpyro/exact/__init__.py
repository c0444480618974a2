"""Inference with the FE itself: the FE-exact posterior (AMIS), profile intervals, the
coordinates they sample in, and least-squares fits through the FE."""
