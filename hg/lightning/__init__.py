"""Lightning side: the HapticGlance module, the episode data module, callbacks and the `hg` CLI."""
from hg.lightning.data import ProbeDataModule
from hg.lightning.module import HapticGlance

__all__ = ["HapticGlance", "ProbeDataModule"]
