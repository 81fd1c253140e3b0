"""Feature extractors for the local-registration pair (camera image, database crop at the predicted pose).

- ``PairedCNN`` stacks the two images channel-wise so the very first convolutions can compare them.
- ``SurfaceCNN`` reads the learned MCL encoder's correlation surface around the prediction (``learning.surface``):
  a small CNN, a soft-argmax of its output (the peak's position: the correction) and pooled features; its NumPy
  twin is ``learning.surface.surface_features``.
- ``CorrelationCNN`` encodes both with one shared (siamese) CNN, correlates the feature maps over a window of
  shifts (a FlowNet-C style cost volume, pooled over the image) and hands the head the scores plus their
  soft-argmax: the shift that best aligns camera and database, which is the correction up to a fixed linear
  map. Matching is built into the architecture, so the policy only has to learn shadow-robust features and
  that map, in far fewer samples than the stacked CNN.

SB3 hands both images channel-first and scaled to [0, 1] (its preprocessing of image spaces).
"""

from __future__ import annotations

import gymnasium as gym

from aerial_loc_env.errors import ConfigError, require_extra

th = require_extra("torch", "rl", "Learned policies")
sb3_torch_layers = require_extra("stable_baselines3.common.torch_layers", "rl", "Learned policies")
sb3_preprocessing = require_extra("stable_baselines3.common.preprocessing", "rl", "Learned policies")
nn = th.nn
F = th.nn.functional


def _pair_shape(observation_space: gym.spaces.Dict, who: str) -> tuple[int, int, int]:
    """(channels, height, width) of the image pair, which must have equal shapes."""
    space = observation_space["image"]
    if observation_space["map"].shape != space.shape:
        raise ConfigError(f"{who}: 'image' and 'map' must have the same shape, got {space.shape} and "
                          f"{observation_space['map'].shape}")
    if sb3_preprocessing.is_image_space_channels_first(space):
        return tuple(space.shape)  # type: ignore[return-value]
    h, w, c = space.shape
    return c, h, w


class PairedCNN(sb3_torch_layers.BaseFeaturesExtractor):
    """A small CNN over [image | map] stacked on channels."""

    def __init__(self, observation_space: gym.spaces.Dict, features_dim: int = 256):
        super().__init__(observation_space, features_dim)
        c, h, w = _pair_shape(observation_space, "PairedCNN")
        # A Nature-DQN-like stem (8x8 stride 4) keeps a 64 px pair cheap to train on one CPU core (a stride-2 stem
        # costs several times more); the flattened grid keeps where things matched.
        self.cnn = nn.Sequential(
            nn.Conv2d(2 * c, 32, 8, stride=4, padding=2), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1, padding=1), nn.ReLU(),
            nn.Flatten(),
        )
        with th.no_grad():
            n = self.cnn(th.zeros(1, 2 * c, h, w)).shape[1]
        self.head = nn.Sequential(nn.Linear(n, features_dim), nn.ReLU())

    def forward(self, obs: dict) -> th.Tensor:
        return self.head(self.cnn(th.cat([obs["image"], obs["map"]], dim=1)))


class CorrelationCNN(sb3_torch_layers.BaseFeaturesExtractor):
    """Siamese encoder + cost volume over shifts of +-``max_shift`` feature pixels + soft-argmax (see above).

    Features: ``features_dim - 2`` ReLU units over the (2 s + 1)^2 correlation scores, then the soft-argmax
    shift (x, y) in units of ``max_shift`` (signed, kept linear so the action head can read it directly).
    """

    def __init__(self, observation_space: gym.spaces.Dict, features_dim: int = 128, max_shift: int = 6,
                 channels: int = 32):
        super().__init__(observation_space, features_dim)
        if features_dim < 3:
            raise ConfigError(f"CorrelationCNN: features_dim = {features_dim} must be >= 3")
        c, h, w = _pair_shape(observation_space, "CorrelationCNN")
        self.encoder = nn.Sequential(
            nn.Conv2d(c, channels // 2, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(channels // 2, channels, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(channels, channels, 1),
        )
        with th.no_grad():
            _, _, fh, fw = self.encoder(th.zeros(1, c, h, w)).shape
        self.max_shift = min(int(max_shift), fh - 1, fw - 1)
        s = self.max_shift
        self.n_shifts = (2 * s + 1) ** 2
        grid = th.arange(-s, s + 1, dtype=th.float32) / max(s, 1)
        gy, gx = th.meshgrid(grid, grid, indexing="ij")
        self.register_buffer("shift_x", gx.reshape(-1), persistent=False)
        self.register_buffer("shift_y", gy.reshape(-1), persistent=False)
        self.log_temperature = nn.Parameter(th.tensor(2.0))
        self.head = nn.Sequential(nn.Linear(self.n_shifts, features_dim - 2), nn.ReLU())

    def _features(self, x: th.Tensor) -> th.Tensor:
        f = self.encoder(x)
        f = f - f.mean(dim=(2, 3), keepdim=True)
        return F.normalize(f, dim=1)

    def cost_volume(self, image: th.Tensor, database: th.Tensor) -> th.Tensor:
        """(B, (2s+1)^2) mean correlation of the camera features with the database features shifted by
        each (dy, dx) (row-major over dy, then dx): high where the camera content sits at that shift."""
        a, b = self._features(image), self._features(database)
        s = self.max_shift
        n, c, h, w = a.shape
        # one grouped convolution: each (sample, channel) of the camera features is the kernel slid over the
        # same channel of the padded database features, then summed over channels
        bp = F.pad(b, (s, s, s, s)).reshape(1, n * c, h + 2 * s, w + 2 * s)
        out = F.conv2d(bp, a.reshape(n * c, 1, h, w), groups=n * c)
        return out.reshape(n, c, -1).sum(dim=1) / (h * w)

    def forward(self, obs: dict) -> th.Tensor:
        scores = self.cost_volume(obs["image"], obs["map"])
        weights = th.softmax(scores * self.log_temperature.exp() * 10.0, dim=1)
        soft = th.stack([(weights * self.shift_x).sum(dim=1), (weights * self.shift_y).sum(dim=1)], dim=1)
        return th.cat([self.head(scores * 10.0), soft], dim=1)


class SurfaceCNN(sb3_torch_layers.BaseFeaturesExtractor):
    """Features of a correlation surface (B, 1, side, side): convolutions (ReLU), one more to a logit per position,
    its softmax's soft-argmax (east, north) in units of the half side, the peak probability, the surface's max,
    mean and std, and the last hidden layer average-pooled to ``pool`` x ``pool``."""

    def __init__(self, observation_space: gym.spaces.Box, channels: tuple[int, ...] = (8, 8),
                 kernels: tuple[int, ...] = (5, 3), pool: int = 3):
        side = int(observation_space.shape[-1])
        super().__init__(observation_space, 6 + int(channels[-1]) * pool * pool)
        layers, cin = [], 1
        for c, k in zip(channels, kernels, strict=True):
            layers.append(nn.Conv2d(cin, int(c), int(k), padding=int(k) // 2))
            cin = int(c)
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Conv2d(cin, 1, 3, padding=1)
        self.pool, self.side = int(pool), side
        self.register_buffer("grid", th.linspace(-1.0, 1.0, side), persistent=False)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        from aerial_loc_env.learning.surface import SURFACE_GAIN

        b = obs.shape[0]
        h = obs.reshape(b, 1, self.side, self.side) * SURFACE_GAIN
        for conv in self.hidden:
            h = F.relu(conv(h))
        p = th.softmax(self.out(h).reshape(b, -1), dim=1)
        pm = p.reshape(b, self.side, self.side)
        soft = th.stack([(pm.sum(1) * self.grid).sum(1), (pm.sum(2) * self.grid).sum(1)], dim=1)
        flat = obs.reshape(b, -1)
        stats = th.stack([p.max(1).values, flat.max(1).values, flat.mean(1), flat.std(1, unbiased=False)], dim=1)
        q = self.side // self.pool
        pooled = F.avg_pool2d(h[:, :, :q * self.pool, :q * self.pool], q).reshape(b, -1)
        return th.cat([soft, stats, pooled], dim=1)


EXTRACTORS = {"paired": PairedCNN, "correlation": CorrelationCNN}
