"""Temporally correlated exploration noise for PPO's Gaussian actions: colored noise, power spectrum ~ 1 / f^beta.

White noise (beta 0, PPO's usual i.i.d. draws) jitters around the mean and cancels out over a few steps: it hardly
explores moving faster or further in one direction. Colored noise keeps the same N(0, 1) marginal per step, so the
policy's log-probs stay those of its Gaussian, but neighbouring steps agree: beta 1 is pink noise (Eberhard et al.,
"Pink Noise Is All You Need", ICLR 2023), and Hollenstein et al. ("Colored Noise in PPO", AAAI 2024) found beta 0.5
best for PPO. One sequence per env and episode, drawn at the episode's start from a seeded generator.
"""

from __future__ import annotations

import numpy as np


def powerlaw_noise(beta: float, n_steps: int, n_dims: int, rng: np.random.Generator) -> np.ndarray:
    """(n_steps, n_dims) Gaussian noise with power spectrum ~ 1 / f^beta along the steps, each step N(0, 1).

    The Timmer & Koenig (1995) construction, as in the `colorednoise` package: random Fourier coefficients scaled by
    f^(-beta / 2), the frequencies below 1 / n_steps held at that floor, then an inverse real FFT, divided by the
    std that construction gives every step (counting the mean and Nyquist terms, which `colorednoise` leaves out)."""
    frequencies = np.fft.rfftfreq(n_steps)
    scale = np.maximum(frequencies, 1.0 / n_steps) ** (-beta / 2.0)
    real = rng.normal(size=(n_dims, frequencies.size)) * scale
    imaginary = rng.normal(size=(n_dims, frequencies.size)) * scale
    # x_t = (X_0 + 2 sum_k Re(X_k e^(2 pi i k t / n)) + X_(n/2) (-1)^t) / n: the mean and an even length's Nyquist
    # coefficient are real (their real part scaled by sqrt(2) to keep their share of the spectrum), the rest complex
    real_only = [0, frequencies.size - 1] if n_steps % 2 == 0 else [0]
    imaginary[:, real_only] = 0.0
    real[:, real_only] *= np.sqrt(2.0)
    weights = np.full(frequencies.size, 4.0)
    weights[real_only] = 2.0
    step_std = np.sqrt(np.sum(weights * scale**2)) / n_steps
    signal = np.fft.irfft(real + 1j * imaginary, n=n_steps, axis=-1) / step_std
    return signal.T.astype(np.float32)


class ColoredNoiseStream:
    """One env's noise, step by step: a fresh `powerlaw_noise` sequence of `n_steps` from `rng` whenever the last runs
    out (make one per episode with `n_steps` its horizon, and an episode's noise is one sequence)."""

    def __init__(self, beta: float, n_dims: int, n_steps: int, rng: np.random.Generator):
        self.draw = lambda: powerlaw_noise(beta, n_steps, n_dims, rng)
        self.sequence, self.position = self.draw(), 0

    def next(self) -> np.ndarray:
        if self.position == len(self.sequence):
            self.sequence, self.position = self.draw(), 0
        self.position += 1
        return self.sequence[self.position - 1]
