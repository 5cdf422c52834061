"""Reuse the network's outputs across the passes of an output-stage fit.

:func:`deltar.evaluation.uncertainty.fit_checkpoint_uncertainty` predicts the same frames
several times, and often with the same network inputs: an outlier rule that sets no
zone of a frame aside, each zone-consistency strength and the pixel collection all give
the network what an earlier pass gave it; only the output stage after it differs. With
its weights fixed, the network is a function of its inputs and of its configuration
(the fit moves one part of it, the head's no-target depth), so
:func:`reuse_network_outputs` answers a repeated (inputs, configuration) pair from a
store instead of running the network again. The fitted numbers are the same as without
the store (tested); only the time changes.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Any

import numpy as np

__all__ = ["NETWORK_INPUTS", "NetworkStore", "network_input_key", "reuse_network_outputs"]

#: The keys of ``DepthEstimator.prepare``'s dict that the network reads.
NETWORK_INPUTS = ("image", "hypotheses", "zone_rects", "zone_valid", "zone_no_target",
                  "zone_targets")
#: Default memory for stored outputs, bytes (about 800 frames of 256 x 320).
DEFAULT_BUDGET_BYTES = 256 * 2**20


def network_input_key(inputs: dict[str, Any], configuration: str = "") -> bytes:
    """A digest of everything the network reads from ``inputs`` (names, dtypes, shapes
    and values of :data:`NETWORK_INPUTS`) and of ``configuration`` (text standing for
    the network's configuration): equal digests, equal outputs of one set of weights."""
    digest = hashlib.blake2b(digest_size=20)
    digest.update(configuration.encode())
    for name in NETWORK_INPUTS:
        value = inputs.get(name)
        digest.update(name.encode())
        if value is None:
            digest.update(b"none")
            continue
        array = np.ascontiguousarray(value)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(memoryview(array).cast("B"))
    return digest.digest()


class NetworkStore:
    """The outputs of one estimator's network, by :func:`network_input_key` of the
    inputs and of ``configuration()``, least recently used dropped first beyond
    ``budget_bytes``.

    Attributes:
        hits, misses: how many calls were answered from the store / ran the network.
    """

    def __init__(self, run, configuration=lambda: "",
                 budget_bytes: int = DEFAULT_BUDGET_BYTES) -> None:
        if budget_bytes < 0:
            raise ValueError(f"budget_bytes must be >= 0, got {budget_bytes}")
        self._run = run
        self._configuration = configuration
        self.budget_bytes = int(budget_bytes)
        self._items: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def __call__(self, inputs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """``run_network(inputs)``: (depth, uncertainty), each (B, 1, h, w) float32
        metres, copies the caller may change."""
        key = network_input_key(inputs, self._configuration())
        stored = self._items.get(key)
        if stored is not None:
            self._items.move_to_end(key)
            self.hits += 1
            return stored[0].copy(), stored[1].copy()
        self.misses += 1
        depth, uncertainty = self._run(inputs)
        size = depth.nbytes + uncertainty.nbytes
        if size <= self.budget_bytes:
            self._items[key] = (depth.copy(), uncertainty.copy())
            self._bytes += size
            while self._bytes > self.budget_bytes:
                _, (old_depth, old_uncertainty) = self._items.popitem(last=False)
                self._bytes -= old_depth.nbytes + old_uncertainty.nbytes
        return depth, uncertainty


def reuse_network_outputs(estimator, budget_bytes: int = DEFAULT_BUDGET_BYTES
                          ) -> NetworkStore:
    """Give ``estimator`` (a :class:`~deltar.inference.estimator.DepthEstimator`) a store
    of its network's outputs: from now on its ``run_network`` runs the network only for
    inputs it has not seen with the network's present configuration (``model.
    network_config``, e.g. its no-target depth; within ``budget_bytes`` of stored
    outputs).

    For an estimator whose weights and backend stay as they are (a fit's private copy);
    ``del estimator.run_network`` removes the store.

    Returns:
        The store (its ``hits`` and ``misses`` count the calls).
    """
    store = NetworkStore(estimator.run_network,
                         lambda: repr(getattr(estimator.model, "network_config", None)),
                         budget_bytes)
    estimator.run_network = store
    return store
