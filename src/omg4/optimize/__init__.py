"""What training (:mod:`omg4.train`) and compression (:mod:`omg4.compress`) optimize with alike: the per-parameter
Adam groups, their learning rates and the surgery that adds, removes and replaces Gaussians with their optimizer
state (:mod:`~omg4.optimize.parameters`); the photometric loss (:mod:`~omg4.optimize.loss`); a batch's loss and
backward (:mod:`~omg4.optimize.step`); and what a segment learns where it meets the one before
(:mod:`~omg4.optimize.teaching`). Below both: neither imports the other's internals."""
