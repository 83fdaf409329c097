"""Scenes for the gRPC servers: locating a tenant's scene folder and an LRU cache of loaded scenes.

``SceneCache.get(folder)`` returns the loaded ``agg.scene.Scene`` of a scene folder, reloading it when the file
it came from changed: a new ``checkpoint.pt`` (training went on) or the final ``model.pt`` appearing. So while a
job trains, renders come from its latest checkpoint, and before the first one ``SceneNotReady`` is raised (the
servers answer FAILED_PRECONDITION). A checkpoint that cannot be read (being replaced) serves the previous
version when there is one, else raises ``SceneUnreadable`` (UNAVAILABLE: retry).
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

from agg.scene import META_FILE, Scene, SceneUnreadable

log = logging.getLogger(__name__)
SCENE_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")  # no separators, no "..": never leaves the root


class SceneLookupError(LookupError):
    """No scene with this id for this tenant (unknown, malformed, or another tenant's)."""


class SceneResolver:
    """scene id -> folder, for a tenant: a root folder (``root/<scene_id>``) or a callable (the job store's
    ``scene_dir``); ``scene_tenant`` says who owns a scene. Every failure is ``SceneLookupError``."""

    def __init__(self, scene_dir: str | Path | Callable[[str], Path], scene_tenant: Callable[[str], str | None]):
        self.root = Path(scene_dir) if isinstance(scene_dir, (str, Path)) else None
        self._resolve = (lambda sid: self.root / sid) if self.root is not None else scene_dir
        self.scene_tenant = scene_tenant

    def folder(self, scene_id: str, tenant: str) -> Path:
        if not isinstance(scene_id, str) or not SCENE_ID_RE.match(scene_id):
            raise SceneLookupError(scene_id)
        if self.scene_tenant(scene_id) != tenant:
            raise SceneLookupError(scene_id)
        try:
            return Path(self._resolve(scene_id))
        except (KeyError, ValueError) as exc:
            raise SceneLookupError(scene_id) from exc

    def candidates(self) -> list[str]:
        """Scene ids under the root folder (none when scenes are located by a callable)."""
        if self.root is None or not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if p.is_dir() and SCENE_ID_RE.match(p.name))


def read_meta(folder: Path) -> dict | None:
    """``scene.json`` of a scene folder, or None when it does not exist (yet) or is unreadable."""
    try:
        return json.loads((folder / META_FILE).read_text())
    except (OSError, ValueError):
        return None


class SceneCache:
    """At most ``capacity`` loaded scenes, least recently used evicted; thread-safe; one load per scene at a time."""

    def __init__(self, capacity: int = 4, device: str = "cpu", loader: Callable[..., Scene] = Scene.load):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity, self.device, self.loader = int(capacity), device, loader
        self._scenes: OrderedDict[str, Scene] = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[str, threading.Lock] = {}
        self.loads = 0  # number of (re)loads, for tests and metrics

    def _current(self, key: str, src: Path, mtime: int) -> Scene | None:
        with self._lock:
            scene = self._scenes.get(key)
            if scene is not None and scene.path == src and scene.mtime_ns == mtime:
                self._scenes.move_to_end(key)
                return scene
        return None

    def get(self, folder: Path) -> Scene:
        key = str(Path(folder).resolve())
        src = Scene.source_file(folder)  # SceneNotReady before the first checkpoint
        mtime = src.stat().st_mtime_ns
        scene = self._current(key, src, mtime)
        if scene is not None:
            return scene
        with self._lock:
            gate = self._loading.setdefault(key, threading.Lock())
        with gate:
            src = Scene.source_file(folder)
            mtime = src.stat().st_mtime_ns
            scene = self._current(key, src, mtime)
            if scene is not None:
                return scene
            try:
                scene = self.loader(folder, device=self.device)
            except SceneUnreadable as exc:
                with self._lock:
                    stale = self._scenes.get(key)
                if stale is None:
                    log.warning("%s", exc)
                    raise
                log.warning("serving the previous version of %s: its checkpoint could not be read", key)
                return stale
            self.loads += 1
            with self._lock:
                self._scenes[key] = scene
                self._scenes.move_to_end(key)
                while len(self._scenes) > self.capacity:
                    self._scenes.popitem(last=False)
        return scene

    def __len__(self) -> int:
        with self._lock:
            return len(self._scenes)
