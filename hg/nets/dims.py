"""The sizes a component is built with, known only once the encoder and the object set are chosen."""
from dataclasses import dataclass


@dataclass(frozen=True)
class Dims:
    """What every injected component (head, policy) is called with: the encoder's output width, the number of
    probes per episode and of classes. YAML gives a component's own options; the model supplies these."""

    rep: int
    n_probes: int
    n_classes: int
