"""Lightning side: the HapticGlance module, the episode data module, callbacks and the `hg` CLI."""
from hg.lightning.data import ProbeDataModule
from hg.lightning.module import HapticGlance, discounted_returns, hybrid_loss

__all__ = ["HapticGlance", "ProbeDataModule", "discounted_returns", "hybrid_loss"]
