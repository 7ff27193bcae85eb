"""What the algorithm (``sb3_collapse.drqv2``), the monitoring callbacks and the experiment code share: the layer
names, the gradient-norm recorder, the persistence of callbacks saved with a model. Nothing here imports them."""
