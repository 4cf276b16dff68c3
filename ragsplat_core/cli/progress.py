"""The one progress-bar helper of the command layer (tqdm on stderr)."""

from __future__ import annotations


def bar(total: int, desc: str, unit: str = "it", initial: int = 0, disable: bool = False, leave: bool = True):
    """A tqdm bar on stderr; use as a context manager or call `.close()`."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=disable, leave=leave,
                dynamic_ncols=True)


def training_bar(total: int, desc: str, initial: int = 0, disable: bool = False, leave: bool = True):
    """(bar, on_step): `on_step(trainer)` advances the bar and shows loss, PSNR on the training view and
    the Gaussian count; pass it to `Trainer.train(on_step=...)`."""
    b = bar(total, desc, "it", initial, disable, leave)

    def on_step(trainer) -> None:
        b.update(1)
        if trainer.step % 10 == 0 or trainer.step == total:
            last = trainer.last
            b.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}", n=trainer.num_gaussians,
                          refresh=False)

    return b, on_step

