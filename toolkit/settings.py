"""Settings models that grow without changing what older runs recorded."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, SerializerFunctionWrapHandler, model_serializer


class AddedOptions(BaseModel):
    """Options added after runs were recorded (``added_off``: name -> its "off" value) are
    left out of the model's serialisation while they are off: the cache keys, resolved
    recipes and written configs of those runs stay the same bytes, so an upgrade reruns no
    stage whose output would come out the same. ``added_unused`` (name -> the boolean
    setting it refines) leaves an added option out while that setting is off, whatever its
    value: it cannot change the output then."""

    added_off: ClassVar[dict[str, Any]] = {}
    added_unused: ClassVar[dict[str, str]] = {}

    @model_serializer(mode="wrap")
    def _leave_out_added_options_when_off(self, handler: SerializerFunctionWrapHandler) -> dict:
        data = handler(self)
        for name, off in self.added_off.items():
            if getattr(self, name) == off:
                data.pop(name, None)
        for name, switch in self.added_unused.items():
            if not getattr(self, switch):
                data.pop(name, None)
        return data
