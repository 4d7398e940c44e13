"""Network architectures: typed specs of the building blocks and the array names they own.

A model file's ``architecture`` card entry is a set of building blocks, each parsed once into a
frozen spec (:class:`MLPSpec`, :class:`ObsSpec`, :class:`HyperSpec`). A spec knows its card entry
(``from_card`` / ``to_card``) and the names and shapes of its arrays (``array_shapes``), so the
torch networks (:mod:`kklcasadi.train.nets`), the CasADi networks (:mod:`kklcasadi.nets.builders`)
and the model files (:mod:`kklcasadi.model.files`) agree by construction. Which blocks a method
uses is decided by its variant (:mod:`kklcasadi.model.variants`). The format is described for users in
``docs/model-format.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Collection, Mapping, Sequence

import numpy as np

from ..validation import Text, error, is_int

__all__ = ["ACTIVATIONS", "ENCODER", "DECODER", "OBS_GRU", "OBS_PROJ", "OBS_GAIN", "HYPER",
           "MLPSpec", "ObsSpec", "HyperSpec", "gru_array_shapes", "lora_target_shapes", "array_name",
           "check_arrays", "check_names", "check_activation", "field_error"]

ACTIVATIONS = ("tanh", "relu", "softplus", "identity")

ENCODER = "encoder"
DECODER = "decoder"
OBS_GRU = "context/gru"
OBS_PROJ = "context/proj/W"
OBS_GAIN = "gain"
HYPER = "hyper"
HYPER_BACKBONE_ACTIVATION = "tanh"


def field_error(where: str, field_name: str, expected: str, received: Any, fix: str) -> ValueError:
    """The package's error (:func:`kklcasadi.validation.error`) for a field of a file or object.

    Parameters
    ----------
    where : str
        The file or object the problem is in.
    field_name : str
        The field (dotted path) or array name.
    expected, received
        What was expected and what was received (``received`` is shown with ``repr``; wrap
        descriptions in :class:`kklcasadi.validation.Text`).
    fix : str
        What the user should do about it.
    """
    shown = field_name if field_name.isprintable() else field_name.encode("unicode_escape").decode("ascii")
    return error(f"{where}: '{shown}'", expected, received, fix)        # a field named "\n" stays on one line


def _positive_field(value: Any, where: str, field_name: str, fix: str) -> int:
    if not is_int(value) or value < 1:
        raise field_error(where, field_name, "a positive integer", value, fix)
    return int(value)


def check_activation(name: Any) -> str:
    """Return ``name`` if it is a known activation, else raise.

    Parameters
    ----------
    name : str
        One of :data:`ACTIVATIONS`.

    Raises
    ------
    ValueError
        If ``name`` is not one of :data:`ACTIVATIONS` (the message lists them).
    """
    if name not in ACTIVATIONS:
        raise error("activation", f"one of {', '.join(ACTIVATIONS)}", name)
    return name


@dataclass(frozen=True)
class MLPSpec:
    """Architecture of one MLP: layer sizes ``[d0, ..., dL]``, the hidden activation and an optional
    linear skip path.

    The card entry is ``{"sizes": [d0, ..., dL], "activation": "tanh"}``, with ``"skip": true`` for a
    network with the skip path. The arrays under a prefix ``P`` are ``P/in_mean`` (d0,), ``P/in_std``
    (d0,), ``P/out_mean`` (dL,), ``P/out_std`` (dL,), for ``i = 0..L-1``: ``P/W{i}`` (d_{i+1}, d_i),
    ``P/b{i}`` (d_{i+1},), and with the skip path ``P/Wskip`` (dL, d0). The network is
    ``(layers(v) + Wskip v) * out_std + out_mean`` with ``v = (x - in_mean) / in_std``: off the data it
    was fit on, the skip path keeps growing where the saturating layers level off.
    """

    sizes: tuple[int, ...]
    activation: str = "tanh"
    skip: bool = False

    def __post_init__(self) -> None:
        sizes = tuple(self.sizes)
        if len(sizes) < 2 or not all(is_int(d) and d >= 1 for d in sizes):
            raise field_error(
                "MLP architecture", "sizes", "at least two positive integers [d_in, ..., d_out]",
                self.sizes, "Give the layer widths, input first.",
            )
        object.__setattr__(self, "sizes", tuple(int(d) for d in sizes))
        check_activation(self.activation)
        if not isinstance(self.skip, bool):
            raise field_error("MLP architecture", "skip", "true or false", self.skip,
                              "Say whether the network has the linear skip path.")

    @classmethod
    def from_card(cls, entry: Any, where: str = "architecture",
                  field_name: str = "mlp") -> MLPSpec:
        """Parse a card entry ``{"sizes": [...], "activation": ...}`` (and ``"skip": true`` for the skip path).

        Parameters
        ----------
        entry : Mapping
            The card entry.
        where, field_name : str
            Used in error messages (the file and the dotted field name).
        """
        fix = 'Write the entry as {"sizes": [d_in, ..., d_out], "activation": "tanh"}.'
        if not isinstance(entry, Mapping):
            raise field_error(where, field_name, "an object with 'sizes' and 'activation'", entry, fix)
        if set(entry) not in ({"sizes", "activation"}, {"sizes", "activation", "skip"}):
            raise field_error(where, field_name, "the keys ['activation', 'sizes'] and optionally 'skip'",
                              sorted(entry), fix)
        sizes = entry["sizes"]
        if (not isinstance(sizes, (list, tuple)) or len(sizes) < 2
                or not all(is_int(d) and d >= 1 for d in sizes)):
            raise field_error(where, f"{field_name}.sizes", "a list of at least two positive integers",
                         sizes, fix)
        if entry["activation"] not in ACTIVATIONS:
            raise field_error(where, f"{field_name}.activation", f"one of {list(ACTIVATIONS)}",
                         entry["activation"], fix)
        skip = entry.get("skip", False)
        if not isinstance(skip, bool):
            raise field_error(where, f"{field_name}.skip", "true or false", skip, fix)
        return cls(tuple(sizes), entry["activation"], skip)

    def to_card(self) -> dict:
        """The card entry of this architecture (``skip`` only where the network has the skip path)."""
        return {"sizes": list(self.sizes), "activation": self.activation, **({"skip": True} if self.skip else {})}

    @property
    def n_in(self) -> int:
        """Input size d0."""
        return self.sizes[0]

    @property
    def n_out(self) -> int:
        """Output size dL."""
        return self.sizes[-1]

    @property
    def layer_shapes(self) -> tuple[tuple[int, int], ...]:
        """Weight shapes ``(d_{i+1}, d_i)`` of the layers, first layer first."""
        return tuple(zip(self.sizes[1:], self.sizes[:-1]))

    def array_shapes(self, prefix: str) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the arrays of this MLP under ``prefix``."""
        shapes = {
            f"{prefix}/in_mean": (self.n_in,),
            f"{prefix}/in_std": (self.n_in,),
            f"{prefix}/out_mean": (self.n_out,),
            f"{prefix}/out_std": (self.n_out,),
        }
        for i, (d_out, d_in) in enumerate(self.layer_shapes):
            shapes[f"{prefix}/W{i}"] = (d_out, d_in)
            shapes[f"{prefix}/b{i}"] = (d_out,)
        if self.skip:
            shapes[f"{prefix}/Wskip"] = (self.n_out, self.n_in)
        return shapes


def gru_array_shapes(prefix: str, nu: int, hidden: int) -> dict[str, tuple[int, ...]]:
    """Names and shapes of a bias-free GRU's arrays: ``P/W_ih`` (3H, nu), ``P/W_hh`` (3H, H)."""
    return {f"{prefix}/W_ih": (3 * hidden, nu), f"{prefix}/W_hh": (3 * hidden, hidden)}


@dataclass(frozen=True)
class ObsSpec:
    """Architecture of the HyperKKL_obs injection.

    Card entries: ``"context": {"hidden": H, "proj": n_l}`` and ``"gain": {mlp}`` with gain
    sizes ``[nz + n_l, ..., nz*nu]``; ``nz`` and ``nu`` follow from the gain sizes.
    """

    hidden: int
    proj: int
    gain: MLPSpec

    def __post_init__(self) -> None:
        where = "obs architecture"
        _positive_field(self.hidden, where, "context.hidden", "Give the GRU width.")
        _positive_field(self.proj, where, "context.proj", "Give the projection width.")
        if self.gain.n_in <= self.proj:
            raise field_error(where, "gain.sizes[0]", f"nz + proj > proj = {self.proj}",
                         self.gain.n_in, "The gain MLP takes [z; l] as input.")
        if self.gain.n_out % self.nz:
            raise field_error(where, "gain.sizes[-1]", f"a multiple of nz = {self.nz} (nz*nu)",
                         self.gain.n_out, "The gain MLP outputs G(z, l) (nz, nu) row-major.")

    @classmethod
    def from_card(cls, architecture: Any, where: str = "architecture") -> ObsSpec:
        """Parse the ``context`` and ``gain`` entries of an architecture mapping."""
        fix = 'Write "context" as {"hidden": H, "proj": n_l}.'
        if not isinstance(architecture, Mapping):
            raise field_error(where, "architecture", "an object", architecture, fix)
        context = architecture.get("context")
        if not isinstance(context, Mapping) or set(context) != {"hidden", "proj"}:
            raise field_error(where, "context", "an object with keys ['hidden', 'proj']", context, fix)
        hidden = _positive_field(context["hidden"], where, "context.hidden", fix)
        proj = _positive_field(context["proj"], where, "context.proj", fix)
        gain = MLPSpec.from_card(architecture.get("gain"), where, "gain")
        try:
            return cls(hidden, proj, gain)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_card(self) -> dict:
        """The ``context`` and ``gain`` card entries."""
        return {"context": {"hidden": self.hidden, "proj": self.proj}, "gain": self.gain.to_card()}

    @property
    def nz(self) -> int:
        """Latent size, ``gain.sizes[0] - proj``."""
        return self.gain.n_in - self.proj

    @property
    def nu(self) -> int:
        """Input size, ``gain.sizes[-1] / nz``."""
        return self.gain.n_out // self.nz

    def array_shapes(self, prefix: str = "") -> dict[str, tuple[int, ...]]:
        """Names and shapes of the injection's arrays (``prefix`` empty in model files)."""
        shapes = gru_array_shapes(array_name(prefix, OBS_GRU), self.nu, self.hidden)
        shapes[array_name(prefix, OBS_PROJ)] = (self.proj, self.hidden)
        shapes.update(self.gain.array_shapes(array_name(prefix, OBS_GAIN)))
        return shapes


@dataclass(frozen=True)
class HyperSpec:
    """Architecture of the HyperKKL_dyn LoRA hypernetwork.

    Card entry ``"hyper": {"hidden": H, "embed": E, "backbone": [64, 64], "rank": r}``. The
    backbone MLP has sizes ``[H + E, *backbone]`` and tanh activation.
    """

    hidden: int
    embed: int
    backbone: tuple[int, ...]
    rank: int

    def __post_init__(self) -> None:
        where, fix = "hyper architecture", "Give positive integers."
        _positive_field(self.hidden, where, "hyper.hidden", fix)
        _positive_field(self.embed, where, "hyper.embed", fix)
        _positive_field(self.rank, where, "hyper.rank", fix)
        backbone = tuple(self.backbone)
        if not backbone or not all(is_int(d) and d >= 1 for d in backbone):
            raise field_error(where, "hyper.backbone", "a non-empty list of positive integers",
                         self.backbone, fix)
        object.__setattr__(self, "backbone", tuple(int(d) for d in backbone))

    @classmethod
    def from_card(cls, architecture: Any, where: str = "architecture") -> HyperSpec:
        """Parse the ``hyper`` entry of an architecture mapping."""
        fix = 'Write "hyper" as {"hidden": H, "embed": E, "backbone": [64, 64], "rank": r}.'
        if not isinstance(architecture, Mapping):
            raise field_error(where, "architecture", "an object", architecture, fix)
        entry = architecture.get("hyper")
        keys = {"hidden", "embed", "backbone", "rank"}
        if not isinstance(entry, Mapping) or set(entry) != keys:
            raise field_error(where, "hyper", f"an object with keys {sorted(keys)}", entry, fix)
        backbone = entry["backbone"]
        if not isinstance(backbone, (list, tuple)):
            raise field_error(where, "hyper.backbone", "a list of positive integers", backbone, fix)
        try:
            return cls(entry["hidden"], entry["embed"], tuple(backbone), entry["rank"])
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_card(self) -> dict:
        """The ``hyper`` card entry."""
        return {"hyper": {"hidden": self.hidden, "embed": self.embed,
                          "backbone": list(self.backbone), "rank": self.rank}}

    @property
    def backbone_spec(self) -> MLPSpec:
        """The backbone MLP, sizes ``[H + E, *backbone]``, tanh."""
        return MLPSpec((self.hidden + self.embed, *self.backbone), HYPER_BACKBONE_ACTIVATION)

    def array_shapes(self, prefix: str, nu: int,
                     target_shapes: Sequence[tuple[int, int]]) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the hypernetwork's arrays.

        Parameters
        ----------
        prefix : str
            ``"hyper"`` in model files.
        nu : int
            Input size (the GRU's input).
        target_shapes : sequence of (d_out, d_in)
            The modulated layers, see :func:`lora_target_shapes`.
        """
        shapes = gru_array_shapes(f"{prefix}/gru", nu, self.hidden)
        shapes[f"{prefix}/embed"] = (len(target_shapes), self.embed)
        shapes.update(self.backbone_spec.array_shapes(f"{prefix}/backbone"))
        n_features = self.backbone[-1]
        for j, (d_out, d_in) in enumerate(target_shapes):
            shapes[f"{prefix}/head{j}/Wa"] = (d_out * self.rank, n_features)
            shapes[f"{prefix}/head{j}/Wb"] = (d_in * self.rank, n_features)
        shapes[f"{prefix}/scale"] = ()
        return shapes


def lora_target_shapes(encoder: MLPSpec, decoder: MLPSpec) -> tuple[tuple[int, int], ...]:
    """The layers HyperKKL_dyn modulates: all encoder layers, then all decoder layers.

    Returns
    -------
    tuple of (d_out, d_in)
        Target ``j`` has weight shape ``(d_out_j, d_in_j)``.
    """
    return encoder.layer_shapes + decoder.layer_shapes


def array_name(prefix: str, name: str) -> str:
    """``"prefix/name"``, or ``name`` when ``prefix`` is empty."""
    return f"{prefix}/{name}" if prefix else name


def check_names(names: Collection[str], shapes: Mapping[str, tuple[int, ...]], where: str, *,
                exact: bool = False) -> None:
    """Check that the array ``names`` hold every name of ``shapes`` (and no other with ``exact``).

    Raises
    ------
    ValueError
        Naming the first missing (or extra) array.
    """
    missing = [name for name in shapes if name not in names]
    if missing:
        raise field_error(where, missing[0], f"an array of shape {shapes[missing[0]]}", Text("missing"),
                     f"{len(missing)} array(s) missing ({', '.join(missing[:5])}"
                     f"{', ...' if len(missing) > 5 else ''}); the weights do not match the "
                     "architecture: save them again from the trained networks.")
    if exact:
        extra = sorted(set(names) - set(shapes))
        if extra:
            raise field_error(where, extra[0], "only the arrays the architecture names",
                         Text("an extra array"),
                         f"Unexpected arrays {extra[:5]}; remove them or fix the architecture.")


def check_arrays(arrays: Any, shapes: Mapping[str, tuple[int, ...]], where: str,
                 *, exact: bool = False) -> None:
    """Check that ``arrays`` holds finite real arrays of the expected shapes.

    Parameters
    ----------
    arrays : Mapping[str, array_like]
        The arrays, by name.
    shapes : Mapping[str, tuple of int]
        Expected names and shapes.
    where : str
        Used in error messages (a file, or an argument name).
    exact : bool
        Also reject arrays that ``shapes`` does not name.

    Raises
    ------
    TypeError
        If ``arrays`` is not a mapping.
    ValueError
        Missing, misshaped, non-numeric or non-finite arrays, and unexpected ones if ``exact``.
    """
    if not isinstance(arrays, Mapping):
        raise error(where, "a mapping of array name -> array", Text(type(arrays).__name__),
                    kind=TypeError)
    check_names(arrays, shapes, where, exact=exact)
    for name, shape in shapes.items():
        value = np.asarray(arrays[name])
        if value.dtype.kind not in "fiu":
            raise field_error(where, name, "a real numeric array", Text(f"dtype {value.dtype}"),
                         "Store float64 arrays.")
        if value.shape != tuple(shape):
            raise field_error(where, name, f"shape {tuple(shape)}", Text(f"shape {value.shape}"),
                         "The weights do not match the architecture; save them again from the "
                         "trained networks, or fix the architecture entry.")
        if not np.all(np.isfinite(value)):
            raise field_error(where, name, "finite values", Text("NaN or inf"),
                         "Training diverged or the file is damaged; retrain or restore the model.")
    for name in shapes:
        if name.endswith(("/in_std", "/out_std")) and not np.all(np.asarray(arrays[name]) > 0):
            raise field_error(where, name, "positive standard deviations",
                         float(np.min(arrays[name])),
                         "Normalisation scales must be > 0; clamp them when computing them.")
