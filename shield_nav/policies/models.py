"""Neural models for rsl-rl 5.x: the paper's depth CNN + GRU actor (and the critic choice).

Paper, "Network Architecture": the actor encodes the 100 x 60 depth image with a CNN (convolution, ReLU, pooling)
into a compact feature ``f_CNN``, concatenates it with the proprioceptive state, feeds the result to a GRU, and an
MLP head turns the GRU output into the parameters of a Gaussian over the 4-D action. The critic is asymmetric: it
sees the noise-free privileged group only, so rsl-rl's own :class:`rsl_rl.models.MLPModel` serves as the critic
(``critic.class_name: "MLPModel"``); no class is needed here for it.

:class:`DepthGRUModel` is written against rsl-rl's model interface (the one ``MLPModel`` / ``CNNModel`` /
``RNNModel`` implement), so the stock ``OnPolicyRunner`` and ``PPO`` run it unchanged with
``actor.class_name: "shield_nav.policies.models:DepthGRUModel"``:

* rollout mode (``masks is None``): observations are one step for all envs, ``depth (N, C, H, W)``,
  ``state (N, S)``; the GRU hidden state ``(L, N, Hd)`` is kept inside the model, reset per env on ``done``;
* batch mode (PPO update): observations are rollout chunks split at dones and zero-padded by rsl-rl's
  ``split_and_pad_trajectories``, ``depth (T, B, C, H, W)``, ``state (T, B, S)`` with ``masks (T, B)``; the GRU
  starts every chunk from the hidden state the storage recorded when the chunk started (truncated BPTT over the
  chunk, exactly as rsl-rl's ``RNNModel``), and the output is un-padded back to ``(T, N_mb, ...)``.

Exports (TorchScript and ONNX) carry the GRU state explicitly: ``(obs, depth, h_in) -> (actions, h_out)``.
"""

from __future__ import annotations

import torch
import torch.nn as nn
from rsl_rl.models import MLPModel
from rsl_rl.modules import MLP, RNN, HiddenState
from tensordict import TensorDict

from shield_nav.policies.export import ExportedDepthGRU

__all__ = [
    "DepthEncoder",
    "DepthGRUModel",
    "ExpertTeacher",
    "HypothesisSelect",
    "expand_single_head",
]


class DepthEncoder(nn.Module):
    """Depth-image encoder: ``[Conv2d -> ReLU (-> MaxPool2d(2))] x K -> Flatten -> Linear -> ReLU``.

    A convolution of kernel ``k`` and stride ``s`` pads by ``k // 2`` for odd ``k`` and not at all for even ``k``
    (so ``k = s`` tiles the image into patches); with ``H_in`` rows it gives
    ``H_conv = floor((H_in + 2 * pad - k) / s) + 1`` and the optional 2 x 2 max pool ``floor(H_conv / 2)`` (same
    for the width). The default stack on a 60 x 100 image (channels 8, 16, 32; kernels 4, 3, 3; strides 4, 1, 1;
    pooling after layers 2 and 3):

    ``(1, 60, 100) -conv4/4-> (8, 15, 25) -conv3-> (16, 15, 25) -pool-> (16, 7, 12) -conv3-> (32, 7, 12)
    -pool-> (32, 3, 6) -flatten-> 576 -linear-> feature_dim``.

    The first layer is a stride-4 patch convolution without pooling because, measured on this 2-core CPU,
    a full-resolution first feature map (e.g. 16 x 30 x 50 after a stride-2 convolution) makes the ReLU and
    pooling passes memory-bound and the encoder 3-6x slower for the same output size (see docs/training.md).
    Every pixel still reaches a filter, so one-pixel-wide poles are not skipped.
    """

    def __init__(
        self,
        input_hw: tuple[int, int],
        in_channels: int,
        channels: tuple[int, ...] | list[int],
        kernel_sizes: tuple[int, ...] | list[int],
        strides: tuple[int, ...] | list[int],
        max_pool: tuple[bool, ...] | list[bool],
        feature_dim: int,
    ) -> None:
        """Build the encoder.

        Args:
            input_hw: Image height and width (rows, columns).
            in_channels: Input channels (1 for a depth image).
            channels: Output channels of each convolution.
            kernel_sizes: Kernel size of each convolution (square).
            strides: Stride of each convolution.
            max_pool: Whether a 2 x 2 max pool follows each convolution.
            feature_dim: Size of the output feature ``f_CNN``.
        """
        super().__init__()
        if not (len(channels) == len(kernel_sizes) == len(strides) == len(max_pool)) or len(channels) == 0:
            raise ValueError(
                "cnn_channels, cnn_kernel_sizes, cnn_strides and cnn_max_pool must be non-empty and of equal length,"
                f" got {list(channels)}, {list(kernel_sizes)}, {list(strides)}, {list(max_pool)}"
            )
        layers: list[nn.Module] = []
        c, (h, w) = in_channels, input_hw
        for c_out, k, st, pool in zip(channels, kernel_sizes, strides, max_pool, strict=True):
            k, st, pad = int(k), int(st), int(k) // 2 if int(k) % 2 else 0
            layers += [nn.Conv2d(c, int(c_out), k, stride=st, padding=pad), nn.ReLU()]
            h, w = (h + 2 * pad - k) // st + 1, (w + 2 * pad - k) // st + 1
            if pool:
                layers.append(nn.MaxPool2d(2))
                h, w = h // 2, w // 2
            if h < 1 or w < 1:
                raise ValueError(f"the CNN stack shrinks a {tuple(input_hw)} image to nothing; use fewer layers")
            c = c_out
        self.conv = nn.Sequential(*layers)
        self.conv_out_shape = (c, h, w)
        """Shape (C, H, W) of the last pooled feature map."""
        self.proj = nn.Sequential(nn.Flatten(start_dim=1), nn.Linear(c * h * w, feature_dim), nn.ReLU())
        self.feature_dim = feature_dim
        """Size of the output feature."""
        for m in self.conv:
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        # Channels-last filters make oneDNN run the whole stack in NHWC: the encoder's forward + backward is 1.7x
        # faster at 128 images and 2.2x at 1,024 on this 2-core CPU (docs/training.md). Same values up to float
        # summation order; state dicts, optimiser state, ``.to(device)`` and copies keep the layout, and
        # checkpoints written before it load unchanged (``load_state_dict`` copies into these tensors).
        self.conv.to(memory_format=torch.channels_last)

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        """Encode images ``(B, C, H, W)`` into features ``(B, feature_dim)``."""
        return self.proj(self.conv(depth))


class HypothesisSelect(nn.Module):
    """Pick one of ``K`` candidate actions by score: ``(..., K * A + K) -> (..., A)``.

    The input holds the ``K`` candidates (``K * A`` values, candidate-major) followed by their ``K`` scores; the
    output is the candidate with the largest score (the first one on ties). Exportable to TorchScript and ONNX
    (``ArgMax`` + ``GatherElements``), so a multi-hypothesis student deploys as a plain ``(obs) -> action`` policy.
    This is the multi-hypothesis output of Loquercio et al. 2021 ("Learning high-speed flight in the wild",
    Science Robotics), there over trajectories, here over the next action.
    """

    def __init__(self, num_hypotheses: int, action_dim: int) -> None:  # noqa: D107
        super().__init__()
        self.num_hypotheses = int(num_hypotheses)
        self.action_dim = int(action_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The best-scored candidate ``(..., A)``."""
        k, a = self.num_hypotheses, self.action_dim
        lead = list(x.shape[:-1])
        flat = x.reshape(-1, k * (a + 1))
        hyps = flat[:, : k * a].reshape(-1, k, a)
        best = flat[:, k * a :].argmax(dim=-1)
        picked = torch.gather(hyps, 1, best.view(-1, 1, 1).expand(-1, 1, a)).squeeze(1)
        return picked.reshape(lead + [a])

    @torch.jit.unused
    def split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Candidates ``(..., K, A)`` and scores ``(..., K)``."""
        k, a = self.num_hypotheses, self.action_dim
        return x[..., : k * a].unflatten(-1, (k, a)), x[..., k * a :]


def expand_single_head(
    state_dict: dict[str, torch.Tensor], model: DepthGRUModel, noise_std: float = 0.02, seed: int = 0
) -> dict[str, torch.Tensor]:
    """Map a single-head :class:`DepthGRUModel` state dict onto the ``K``-hypothesis ``model`` (a warm start).

    Every weight is copied; the last layer of the head is repeated for each candidate, each copy perturbed by
    Gaussian noise of ``noise_std`` (so the winner-takes-all loss can tell them apart), and the score rows start
    at zero (all candidates equally likely). With ``noise_std = 0`` the new model acts exactly as the old one.
    """
    k = model.num_hypotheses
    if k < 2:
        raise ValueError("expand_single_head needs a model with num_hypotheses >= 2")
    head = [key for key in state_dict if key.startswith("mlp.")]
    if not head or any(key.startswith("mlp.0.0.") for key in head):
        raise ValueError("expand_single_head: the state dict is not a single-head DepthGRUModel's")
    last = max(int(key.split(".")[1]) for key in head)
    gen = torch.Generator().manual_seed(seed)
    out: dict[str, torch.Tensor] = {}
    for key, value in state_dict.items():
        if not key.startswith("mlp."):
            out[key] = value
            continue
        _, idx, name = key.split(".", 2)
        if int(idx) != last:
            out[f"mlp.0.{idx}.{name}"] = value
            continue
        copies = [value + noise_std * torch.randn(value.shape, generator=gen, dtype=value.dtype) for _ in range(k)]
        scores = value.new_zeros((k, *value.shape[1:]))
        out[f"mlp.0.{idx}.{name}"] = torch.cat([*copies, scores], dim=0)
    return out


def expand_state_inputs(
    state_dict: dict[str, torch.Tensor], model: DepthGRUModel, new_mean: float = 1.0, new_std: float = 0.25
) -> dict[str, torch.Tensor]:
    """Map a :class:`DepthGRUModel` state dict onto ``model`` whose state has more values at its end (a warm start).

    The new state values (e.g. a ``memory`` group listed after ``state``) enter the GRU through zero weights, so the
    new model acts exactly as the old one until training moves them. Their normaliser starts at ``new_mean`` and
    ``new_std`` (the old values' statistics are kept; with the old sample count they then move slowly).
    """
    s_new = int(model.obs_dim)
    key = "rnn.rnn.weight_ih_l0"
    if key not in state_dict or "obs_normalizer._mean" not in state_dict:
        raise ValueError("expand_state_inputs: the state dict is not a DepthGRUModel's with a state normaliser")
    s_old = int(state_dict["obs_normalizer._mean"].shape[-1])
    if not 0 < s_old < s_new:
        raise ValueError(f"expand_state_inputs: the state dict's state has {s_old} values; the model's {s_new}")
    out = dict(state_dict)
    w = state_dict[key]  # (3 Hd, S_old + F)
    out[key] = torch.cat([w[:, :s_old], w.new_zeros((w.shape[0], s_new - s_old)), w[:, s_old:]], dim=1)
    extra = s_new - s_old
    for name, value in (("_mean", new_mean), ("_var", new_std**2), ("_std", new_std)):
        old = state_dict[f"obs_normalizer.{name}"]
        out[f"obs_normalizer.{name}"] = torch.cat([old, old.new_full((*old.shape[:-1], extra), value)], dim=-1)
    return out


def widen_encoder(state_dict: dict[str, torch.Tensor], model: DepthGRUModel) -> dict[str, torch.Tensor]:
    """Map a :class:`DepthGRUModel` state dict onto ``model`` whose depth encoder is wider (a warm start).

    ``model`` has the same convolution stack (layer count, kernels, strides, pooling) with at least as many channels
    in every layer and at least as many image features. Each layer's old filters keep their weights and read only
    the old input channels (zero weights on the new ones); the new filters and features keep ``model``'s own
    initial weights, and the GRU reads the new features through zero weights. So the wider model acts exactly as
    the old one, and training grows the new channels from there (the function-preserving widening of Chen et al.,
    "Net2Net", 2016, with zero rather than split outgoing weights). The rest of the state dict is taken unchanged.
    """
    own = model.state_dict()
    convs = sorted(
        {int(k.split(".")[2]) for k in own if k.startswith("encoder.conv.") and k.endswith(".weight")}
    )  # indices of the Conv2d layers inside encoder.conv
    keys = [f"encoder.conv.{i}.weight" for i in convs] + ["encoder.proj.1.weight", "rnn.rnn.weight_ih_l0"]
    missing = [k for k in keys if k not in state_dict]
    if missing:
        raise ValueError(f"widen_encoder: the state dict lacks {missing} (not a DepthGRUModel with the same stack)")
    out = dict(state_dict)
    c_in_old = c_in_new = int(own[keys[0]].shape[1])
    for i in convs:
        old, new = state_dict[f"encoder.conv.{i}.weight"], own[f"encoder.conv.{i}.weight"]
        if old.shape[2:] != new.shape[2:] or old.shape[1] != c_in_old or new.shape[1] != c_in_new:
            raise ValueError(f"widen_encoder: convolution {i} is {tuple(old.shape)} in the state dict and "
                             f"{tuple(new.shape)} in the model: not the same stack")  # fmt: skip
        if old.shape[0] > new.shape[0]:
            raise ValueError(f"widen_encoder: convolution {i} has {old.shape[0]} channels in the state dict, "
                             f"{new.shape[0]} in the model (narrowing is not a warm start)")  # fmt: skip
        w = new.clone()
        w[: old.shape[0]] = 0.0
        w[: old.shape[0], :c_in_old] = old
        b = own[f"encoder.conv.{i}.bias"].clone()
        b[: old.shape[0]] = state_dict[f"encoder.conv.{i}.bias"]
        out[f"encoder.conv.{i}.weight"], out[f"encoder.conv.{i}.bias"] = w, b
        c_in_old, c_in_new = int(old.shape[0]), int(new.shape[0])
    # The flattened map is channel-major: old channel c's values sit at c * HW .. (c + 1) * HW - 1 in both.
    c_new, h, w_ = model.encoder.conv_out_shape
    hw = h * w_
    old, new = state_dict["encoder.proj.1.weight"], own["encoder.proj.1.weight"]
    if old.shape[1] != c_in_old * hw or old.shape[0] > new.shape[0]:
        raise ValueError(f"widen_encoder: the image projection is {tuple(old.shape)} in the state dict and "
                         f"{tuple(new.shape)} in the model")  # fmt: skip
    p = new.clone()
    p[: old.shape[0]] = 0.0
    p[: old.shape[0], : c_in_old * hw] = old
    pb = own["encoder.proj.1.bias"].clone()
    pb[: old.shape[0]] = state_dict["encoder.proj.1.bias"]
    out["encoder.proj.1.weight"], out["encoder.proj.1.bias"] = p, pb
    f_old, f_new = int(old.shape[0]), int(new.shape[0])
    g = state_dict["rnn.rnn.weight_ih_l0"]  # (3 Hd, S + F_old): the image features are the last columns
    out["rnn.rnn.weight_ih_l0"] = torch.cat([g, g.new_zeros((g.shape[0], f_new - f_old))], dim=1)
    return out


def encoder_widths(state_dict: dict[str, torch.Tensor]) -> list[int]:
    """A depth encoder's widths from its weights: each convolution's output channels, then the image features."""
    return [int(v.shape[0]) for k, v in state_dict.items() if k.startswith("encoder.") and k.endswith(".weight")]


def encoder_is_wider(state_dict: dict[str, torch.Tensor], model: DepthGRUModel) -> bool:
    """Whether ``model``'s depth encoder has more channels or image features than the state dict's."""
    old, new = encoder_widths(state_dict), encoder_widths(model.state_dict())
    return len(old) == len(new) and any(n > o for o, n in zip(old, new, strict=True))


class DepthGRUModel(MLPModel):
    """Depth CNN + GRU + MLP actor for rsl-rl 5.x (paper, "Network Architecture").

    ``x_t = [normalize(state_t), CNN(depth_t)]``; ``y_t, h_t = GRU(x_t, h_{t-1})``; ``mu_t = MLP(y_t)``; the action
    distribution is built from ``mu_t`` by ``distribution_cfg`` (e.g. rsl-rl's ``GaussianDistribution`` with a
    state-independent learnable std).

    Observation groups of the ``obs_set`` (e.g. ``actor: ["depth", "state"]``) are split by rank, as rsl-rl's
    ``CNNModel`` does: exactly one 4-D group ``(N, C, H, W)`` (the depth image, already normalised to [0, 1] by
    the env, so it is not normalised again) and one or more 2-D groups ``(N, S_i)`` concatenated in the listed
    order into the state ``(N, S)``, optionally normalised by rsl-rl's ``EmpiricalNormalization``.
    """

    is_recurrent: bool = True
    """Whether the model contains a recurrent module (PPO then uses the recurrent mini-batch generator)."""

    def __init__(
        self,
        obs: TensorDict,
        obs_groups: dict[str, list[str]],
        obs_set: str,
        output_dim: int,
        hidden_dims: tuple[int, ...] | list[int] = (128, 64),
        activation: str = "elu",
        obs_normalization: bool = True,
        distribution_cfg: dict | None = None,
        cnn_channels: tuple[int, ...] | list[int] = (8, 16, 32),
        cnn_kernel_sizes: tuple[int, ...] | list[int] = (4, 3, 3),
        cnn_strides: tuple[int, ...] | list[int] = (4, 1, 1),
        cnn_max_pool: tuple[bool, ...] | list[bool] = (False, True, True),
        cnn_feature_dim: int = 64,
        rnn_hidden_dim: int = 128,
        rnn_num_layers: int = 1,
        num_hypotheses: int = 1,
    ) -> None:
        """Build the model from one batch of observations (only shapes are read).

        Args:
            obs: Observation TensorDict, e.g. ``depth (N, 1, 60, 100)`` and ``state (N, 21)``.
            obs_groups: Mapping of observation sets to lists of observation groups.
            obs_set: The set this model reads (``"actor"``).
            output_dim: Action dimension (4).
            hidden_dims: Hidden sizes of the MLP head after the GRU.
            activation: Activation of the MLP head (rsl-rl name, e.g. ``"elu"``).
            obs_normalization: Normalise the 1-D state groups with running mean/std (updated by PPO after
                each update, frozen in exports).
            distribution_cfg: rsl-rl distribution config, e.g. ``{"class_name": "GaussianDistribution",
                "init_std": 1.0, "std_type": "scalar"}``. ``None`` gives a deterministic model.
            cnn_channels: Output channels of each convolution.
            cnn_kernel_sizes: Kernel size of each convolution.
            cnn_strides: Stride of each convolution.
            cnn_max_pool: Whether a 2 x 2 max pool follows each convolution.
            cnn_feature_dim: Size of the visual feature ``f_CNN``.
            rnn_hidden_dim: GRU hidden size ``Hd`` (the MLP head's input).
            rnn_num_layers: Number of stacked GRU layers ``L``.
            num_hypotheses: ``K``. With ``K > 1`` the MLP head outputs ``K`` candidate actions and ``K`` scores and
                the model acts with the best-scored candidate (:class:`HypothesisSelect`); trained by
                :class:`shield_nav.algorithms.distillation.MultiHypothesisDistillation`. ``1``: the paper's single head.
        """
        if int(num_hypotheses) < 1:
            raise ValueError(f"DepthGRUModel: num_hypotheses must be >= 1, got {num_hypotheses}")
        self.latent_dim = rnn_hidden_dim  # read by _get_latent_dim() inside MLPModel.__init__
        # MLPModel.__init__ calls our _get_obs_dim (splits 1-D / 2-D groups), builds the normaliser over the 1-D
        # state (S values), the distribution and the MLP head (Hd -> hidden_dims -> distribution input).
        super().__init__(
            obs, obs_groups, obs_set, output_dim, hidden_dims, activation, obs_normalization, distribution_cfg
        )
        c, h, w = self.depth_shape
        self.encoder = DepthEncoder(
            (h, w), c, cnn_channels, cnn_kernel_sizes, cnn_strides, cnn_max_pool, cnn_feature_dim
        )
        # GRU input: S state values + F image features.
        self.rnn = RNN(self.obs_dim + cnn_feature_dim, rnn_hidden_dim, rnn_num_layers, "gru")
        self.num_hypotheses = int(num_hypotheses)
        self.last_hypotheses: torch.Tensor | None = None
        """Candidates ``(..., K, A)`` of the last forward pass (``K > 1`` only; read by the multi-hypothesis loss)."""
        self.last_scores: torch.Tensor | None = None
        """Their scores ``(..., K)`` (logits of which candidate the expert's action is nearest to)."""
        if self.num_hypotheses > 1:
            action_dim = self.mlp[-1].out_features  # the distribution's input (the mean, for a scalar std)
            core = MLP(rnn_hidden_dim, self.num_hypotheses * (action_dim + 1), hidden_dims, activation)
            self.mlp = nn.Sequential(core, HypothesisSelect(self.num_hypotheses, action_dim))

    def forward(
        self,
        obs: TensorDict,
        masks: torch.Tensor | None = None,
        hidden_state: HiddenState = None,
        stochastic_output: bool = False,
    ) -> torch.Tensor:
        """rsl-rl's ``MLPModel.forward``; with ``K > 1`` hypotheses it also keeps the candidates and scores."""
        if self.num_hypotheses == 1:
            return super().forward(obs, masks, hidden_state, stochastic_output)
        raw = self.mlp[0](self.get_latent(obs, masks, hidden_state))  # (..., K * A + K)
        self.last_hypotheses, self.last_scores = self.mlp[1].split(raw)
        mean = self.mlp[1](raw)  # (..., A): the best-scored candidate
        if self.distribution is None:
            return mean
        if stochastic_output:
            self.distribution.update(mean)
            return self.distribution.sample()
        return self.distribution.deterministic_output(mean)

    @property
    def mean_head(self) -> nn.Module:
        """The module whose output is the mean action ``(..., A)``, the distribution's input.

        The MLP head, or with ``K > 1`` its candidate selection. Read by
        :class:`shield_nav.algorithms.anchored.AnchoredPPO`.
        """
        return self.mlp if self.num_hypotheses == 1 else self.mlp[1]

    # ------------------------------------------------------------------------------------------------ forward

    def get_latent(
        self, obs: TensorDict, masks: torch.Tensor | None = None, hidden_state: HiddenState = None
    ) -> torch.Tensor:
        """GRU output for rollout mode ``(N, Hd)`` or batch mode ``(T, N_mb, Hd)`` (see the module docstring)."""
        state = self.obs_normalizer(torch.cat([obs[g] for g in self.obs_groups], dim=-1))  # (N, S) or (T, B, S)
        depth = obs[self.depth_group]  # (N, C, H, W) or (T, B, C, H, W)
        if masks is None:
            feat = self.encoder(depth)  # (N, F)
        else:
            # Padded chunks: encode only the valid steps (masks (T, B) True), M = masks.sum() <= T * B images;
            # padded steps get a zero feature. They lie after each chunk's end, so the causal GRU never feeds
            # them into a valid output, and rsl-rl's unpad_trajectories drops them.
            feat = depth.new_zeros((*masks.shape, self.encoder.feature_dim))  # (T, B, F)
            feat[masks] = self.encoder(depth[masks])  # (M, C, H, W) -> (M, F)
        x = torch.cat([state, feat], dim=-1)  # (..., S + F)
        out = self.rnn(x, masks, hidden_state)  # rollout: (1, N, Hd); batch: (T, N_mb, Hd), unpadded
        return out.squeeze(0) if masks is None else out

    # ------------------------------------------------------------------------------------------------ hidden state

    def reset(self, dones: torch.Tensor | None = None, hidden_state: HiddenState = None) -> None:
        """Zero the hidden state of envs with ``dones == 1`` (``dones`` (N,)), or set/clear all of it."""
        self.rnn.reset(dones, hidden_state)

    def get_hidden_state(self) -> HiddenState:
        """The GRU hidden state ``(L, N, Hd)``, or ``None`` before the first step / after a full reset."""
        return self.rnn.hidden_state  # type: ignore[return-value]

    def detach_hidden_state(self, dones: torch.Tensor | None = None) -> None:
        """Cut the graph through the hidden state (all envs, or those with ``dones == 1``)."""
        self.rnn.detach_hidden_state(dones)

    # ------------------------------------------------------------------------------------------------ export

    def as_jit(self) -> nn.Module:
        """A TorchScript-able copy, ``forward(obs, depth, h_in) -> (actions, h_out)`` (:class:`ExportedDepthGRU`)."""
        return ExportedDepthGRU(self)

    def as_onnx(self, verbose: bool = False) -> nn.Module:
        """An ONNX-exportable copy with ``get_dummy_inputs``, ``input_names`` and ``output_names`` (rsl-rl API)."""
        return ExportedDepthGRU(self, verbose=verbose)

    # ------------------------------------------------------------------------------------------------ internals

    def _get_obs_dim(self, obs: TensorDict, obs_groups: dict[str, list[str]], obs_set: str) -> tuple[list[str], int]:
        """Split the set's groups: one 4-D image group (stored on ``self``) and the 1-D groups (returned, with S)."""
        groups_1d: list[str] = []
        dim_1d = 0
        groups_2d: list[str] = []
        for g in obs_groups[obs_set]:
            shape = tuple(obs[g].shape)
            if len(shape) == 4:  # (N, C, H, W)
                groups_2d.append(g)
            elif len(shape) == 2:  # (N, S_g)
                groups_1d.append(g)
                dim_1d += shape[-1]
            else:
                raise ValueError(f"DepthGRUModel: group '{g}' has shape {shape}; expected (N, S) or (N, C, H, W)")
        if len(groups_2d) != 1:
            raise ValueError(
                f"DepthGRUModel needs exactly one image group (N, C, H, W) in '{obs_set}', got {groups_2d}"
            )
        if not groups_1d:
            raise ValueError(f"DepthGRUModel needs at least one 1-D state group (N, S) in '{obs_set}'")
        self.depth_group = groups_2d[0]
        self.depth_shape = tuple(int(v) for v in obs[self.depth_group].shape[1:])  # (C, H, W)
        return groups_1d, dim_1d

    def _get_latent_dim(self) -> int:
        """The MLP head reads the GRU output (Hd values)."""
        return self.latent_dim


class ExpertTeacher(nn.Module):
    """A parameter-free "teacher" for rsl-rl's ``Distillation`` that returns a scripted expert's action.

    The env adapter computes the expert's normalised action for every visited state as the ``expert`` observation
    group (``envs.rsl_rl.RslRlVecEnv(expert=...)``); this model hands that group to the algorithm as the label, so
    the stock ``DistillationRunner`` runs DAgger against a scripted privileged expert (the oracle) instead of a
    trained MLP teacher. Use as ``teacher.class_name: "shield_nav.policies.models:ExpertTeacher"`` with
    ``obs_groups.teacher: [expert]``. It has no weights and no hidden state.
    """

    is_recurrent = False

    def __init__(
        self, obs: TensorDict, obs_groups: dict[str, list[str]], obs_set: str, output_dim: int, **kwargs: object
    ) -> None:  # noqa: D107
        super().__init__()
        groups = obs_groups[obs_set]
        if len(groups) != 1:
            raise ValueError(f"ExpertTeacher reads exactly one observation group in '{obs_set}', got {groups}")
        self.group = groups[0]
        shape = tuple(obs[self.group].shape)
        if shape[1:] != (output_dim,):
            raise ValueError(f"ExpertTeacher: group '{self.group}' has shape {shape}; expected (N, {output_dim})")

    def forward(
        self,
        obs: TensorDict,
        masks: torch.Tensor | None = None,
        hidden_state: HiddenState = None,
        stochastic_output: bool = False,
    ) -> torch.Tensor:
        """The expert's action (N, A), as given."""
        return obs[self.group].float()

    def reset(self, dones: torch.Tensor | None = None, hidden_state: HiddenState = None) -> None:
        """Nothing to reset (the labels come in the observation; a scripted expert keeps its own state)."""

    def get_hidden_state(self) -> HiddenState:
        """None (no hidden state)."""
        return None

    def detach_hidden_state(self, dones: torch.Tensor | None = None) -> None:
        """Nothing to detach."""
