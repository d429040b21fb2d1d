"""Models that render: every file omg4 reads, loaded as a render-only model.

:func:`load_model` recognizes a checkpoint, an ``.omg4`` file, an ``.omg4`` sequence or a training run's folder;
:class:`WindowedModel` (every single model: frames touch only their time window's Gaussians),
:class:`CompactModel` (a decoded ``.omg4`` file: codebook lookups and appearance MLPs) and :class:`SequenceModel`
(a long capture's segments, decoded when first shown). This package sits above the codec (bytes) and the
Gaussians (math) and below evaluation, training and compression; it imports no training or compression code.
"""

from omg4.models.compact import CompactModel, load_omg4
from omg4.models.loading import load_model, load_segmented_run
from omg4.models.sequence import SequenceModel, load_sequence
from omg4.models.windowed import WindowedModel

__all__ = ["CompactModel", "SequenceModel", "WindowedModel", "load_model", "load_omg4", "load_segmented_run",
           "load_sequence"]
