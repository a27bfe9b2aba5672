"""What the policy sees: a frozen encoder's embedding of the stream of frames an environment produces.

An observer is fed every new frame of `num_envs` environments stepped together (rendered frames, the
simulator state, and which environments start an episode with this frame) and returns the embedding of
the clip ending at that frame. Encoders with a `streaming(num_envs)` method (mfTCN, TCN, true state,
random state) provide their own incremental version; any other encoder is served by `ClipWindowObserver`,
which keeps the raw frames of the lookback window and calls the encoder's batch `embed`. Either way the
clip follows the rule of `mftcn_bench.data.clips` (frames before an episode's first clamp to it), so a
policy sees exactly the embeddings the encoder gives the same episode offline. The state reaches the encoder
only if it declares it (`encoders.privileged`).
"""

from __future__ import annotations

import numpy as np

from mftcn_bench.data.clips import ClipRing
from mftcn_bench.encoders.base import ClipBatch, Encoder, HistoryStream, StreamingEncoder, check_embeddings
from mftcn_bench.encoders.privileged import declared_inputs, visible

# What an environment feeds: every new frame through `push` (embedded) or `observe` (history only).
Observer = HistoryStream


class ClipWindowObserver:
    """Keeps each environment's last `lookback` frames (and states, for an encoder that declares them);
    embeds clips with `encoder.embed`."""

    def __init__(self, encoder: Encoder, num_envs: int) -> None:
        info = encoder.info
        self.encoder, self.num_envs = encoder, num_envs
        self.lookback = info.lookback
        self._reads_state = "state" in declared_inputs(encoder)
        self._frames = ClipRing(info.frames, info.stride, num_envs)  # [E, lookback, H, W, 3]
        self._state = ClipRing(info.frames, info.stride, num_envs)   # [E, lookback, S]
        self._pixels: bool | None = None

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        if self._pixels is None:
            self._pixels = frames is not None
        if self._reads_state:
            self._state.push(np.asarray(state, dtype=np.float64), episode_start)
        if self._pixels:
            self._frames.push(frames, episode_start)

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        self.observe(frames, episode_start, state)
        state_clip = self._state.clip() if self._reads_state else visible(self.encoder, "state", state)
        clip_frames = (self._frames.clip() if self._pixels
                       else np.zeros((self.num_envs, self.encoder.info.frames, 1, 1, 3), dtype=np.uint8))
        out = self.encoder.embed(ClipBatch(clip_frames, state_clip))
        return check_embeddings(self.encoder, out, self.num_envs)


class _StreamingObserver:
    def __init__(self, encoder: StreamingEncoder, num_envs: int) -> None:
        self.encoder, self.num_envs = encoder, num_envs
        self._stream = encoder.streaming(num_envs)

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        out = self._stream.push(frames, episode_start, visible(self.encoder, "state", state))
        return check_embeddings(self.encoder, out, self.num_envs)

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        if isinstance(self._stream, HistoryStream):
            self._stream.observe(frames, episode_start, visible(self.encoder, "state", state))
        else:
            self._stream.push(frames, episode_start, visible(self.encoder, "state", state))


class StateObserver:
    """The true state as the true-state encoder gives it (cartpole's angle as sin and cos, so a spinning
    pole's unbounded angle never reaches the policy), for expert policies trained on true state."""

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        from mftcn_bench.encoders.baselines import state_embedding

        return state_embedding(np.asarray(state, dtype=np.float64)).astype(np.float32)

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        """The state has no history."""


def make_observer(encoder: Encoder, num_envs: int) -> Observer:
    """The encoder's own streaming embedder when it has one, otherwise a clip window over `embed`."""
    if isinstance(encoder, StreamingEncoder):
        return _StreamingObserver(encoder, num_envs)
    return ClipWindowObserver(encoder, num_envs)
