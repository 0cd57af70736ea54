"""Progress of a catalogue run or a scan: a live bar on a terminal, periodic lines otherwise."""

from __future__ import annotations

import time
from collections import Counter

__all__ = ["Progress", "Bar", "Lines"]


class Progress:
    """Counts assets and clusters; subclasses decide how to show them."""

    def __init__(self, stream=None, every=10.0):
        self.stream = stream
        self.every = every

    @classmethod
    def for_stream(cls, mode, stream):
        if mode == "none":
            return cls()
        tty = hasattr(stream, "isatty") and stream.isatty()
        if mode == "bar" or (mode == "auto" and tty):
            return Bar(stream)
        return Lines(stream)

    def start(self, n_assets, clusters_per_asset):
        self.assets, self.assets_done = n_assets, 0
        self.estimate, self.planned, self.planned_clusters = clusters_per_asset, 0, 0
        self.clusters_done = 0
        self.t0 = self.last = time.monotonic()

    def start_scan(self, n_suspects):
        """Count suspects and their verdicts (a scan) instead of assets and clusters."""
        self.start(n_suspects, 0)
        self.verdicts = Counter()

    def suspect_done(self, verdict):
        self.verdicts[verdict] += 1
        self.asset_done()

    @property
    def clusters(self):
        """Clusters of planned assets plus the estimate for the others."""
        return self.planned_clusters + self.estimate * (self.assets - self.planned)

    def plan_done(self, n_clusters):
        self.planned += 1
        self.planned_clusters += n_clusters
        self.show()

    def cluster_done(self):
        self.clusters_done += 1
        self.show()

    def asset_done(self):
        self.assets_done += 1
        self.show(force=self.assets_done == self.assets)

    def eta(self):
        done = self.assets_done + self.clusters_done / max(self.clusters, 1) * 0.5
        if done <= 0:
            return None
        elapsed = time.monotonic() - self.t0
        return max(0.0, elapsed * (self.assets / done - 1)) if self.assets else 0.0

    def text(self):
        eta = self.eta()
        eta_text = "?" if eta is None else f"{eta:.0f}s"
        if hasattr(self, "verdicts"):
            said = ", ".join(f"{n} {v}" for v, n in sorted(self.verdicts.items()))
            return (f"suspects {self.assets_done}/{self.assets}{f' ({said})' if said else ''}, "
                    f"elapsed {time.monotonic() - self.t0:.0f}s, ETA {eta_text}")
        return (f"assets {self.assets_done}/{self.assets}, clusters {self.clusters_done}/{self.clusters}, "
                f"elapsed {time.monotonic() - self.t0:.0f}s, ETA {eta_text}")

    def show(self, force=False):
        pass

    def finish(self):
        pass


class Lines(Progress):
    def show(self, force=False):
        now = time.monotonic()
        if force or now - self.last >= self.every:
            self.last = now
            print(f"[pointmark] {self.text()}", file=self.stream, flush=True)


class Bar(Progress):
    def show(self, force=False):
        width = 30
        filled = int(width * self.assets_done / max(self.assets, 1))
        bar = "#" * filled + "-" * (width - filled)
        print(f"\r[{bar}] {self.text()}   ", end="", file=self.stream, flush=True)

    def finish(self):
        print(file=self.stream, flush=True)
