"""What a scene's imagery layers and terrain server did, frame after frame: their figures for the
frame's statistics, each kind of failure said once on stderr, and strict mode's error."""

from __future__ import annotations

from typing import Any

from lodscape.imagery.layers import server_figures, warn_stderr
from lodscape.imagery.sources import ImageryError

__all__ = ["ImageryWatch"]


class ImageryWatch:
    """Watches ``provider``'s imagery layers (and the terrain server under its wrappings)."""

    def __init__(self, provider: Any, timeout: float, strict: bool) -> None:
        self.layers: list[Any] = list(provider.layers)
        self.server = _terrain_server(provider)
        self.timeout = timeout
        self.strict = strict
        self._said_late = False
        self._said: set[str] = set()

    def failures(self) -> dict[str, int]:
        """Failed imagery tiles by kind, all layers together, since the scene opened."""
        out: dict[str, int] = {}
        for layer in self.layers:
            for kind, n in layer.failures.items():
                out[kind] = out.get(kind, 0) + n
        return out

    def after(self, loader: Any, late: int) -> dict[str, int]:
        """After a frame (``late``: the loader's late count before it): the figures, the
        notices not said yet, and strict mode's error for any failure."""
        if loader.late > late and not self._said_late:
            self._said_late = True
            warn_stderr(
                f"imagery: {loader.late - late} tiles had not come after the "
                f"{self.timeout:g} s imagery timeout; drawn without them (--imagery-timeout)"
            )
        out: dict[str, int] = {}
        if self.layers:
            out = {**server_figures(self.layers), "imagery_missed": loader.missed}
            fails = self.failures()
            out.update((f"imagery_{k.replace('-', '_')}", n) for k, n in sorted(fails.items()))
        if self.server is not None:
            for name, n in self.server.server_figures().items():
                out[name] = out.get(name, 0) + n
            # each kind of failure said once, after a frame drawn without those tiles
            for kind, line in self.server.notices().items():
                if kind not in self._said:
                    self._said.add(kind)
                    warn_stderr(line)
        if self.strict:
            self._refuse(loader)
        return out

    def _refuse(self, loader: Any) -> None:
        for layer in self.layers:
            if layer.failed:
                kinds = ", ".join(f"{n} {k}" for k, n in sorted(layer.failures.items()))
                raise ImageryError(
                    f"imagery layer {layer.index} ({layer.name}) failed ({kinds}) and "
                    "--imagery-strict was given"
                )
        if loader.missed:
            raise ImageryError(
                f"{loader.missed} imagery tiles did not come within the imagery timeout "
                "and --imagery-strict was given"
            )


def _terrain_server(provider: Any) -> Any:
    """The terrain server under a provider's imagery wrappings (None: no server)."""
    from lodscape.store.remote import RemoteProvider

    while not isinstance(provider, RemoteProvider):
        provider = getattr(provider, "base", None)
        if provider is None:
            return None
    return provider
