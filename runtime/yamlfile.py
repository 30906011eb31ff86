"""YAML documents read strictly: a key written twice in one mapping is an error, not a silent
override (docs/design.md section 10.2). PyYAML's `safe_load` keeps the last of two equal keys, so a
config or jobs file with `iterations:` twice under one heading ran with one of them unseen."""

from __future__ import annotations

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import ScalarNode


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a mapping with two equal keys (merge keys `<<` excepted: what
    they merge may be overridden, as YAML intends)."""


def _mapping_without_repeats(loader: _UniqueKeyLoader, node) -> dict:
    seen: dict = {}
    for key_node, _ in node.value:
        if not isinstance(key_node, ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
            continue  # unhashable keys are refused by construct_mapping itself
        key = loader.construct_object(key_node)
        try:
            first = seen.setdefault(key, key_node)
        except TypeError:
            continue
        if first is not key_node:
            raise ConstructorError(f"while reading a mapping (line {first.start_mark.line + 1})",
                                   node.start_mark, f"the key {key!r} is written twice",
                                   key_node.start_mark)
    loader.flatten_mapping(node)
    return loader.construct_mapping(node, deep=True)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                                 _mapping_without_repeats)


def load_yaml_text(text: str):
    """The document in `text`, as `yaml.safe_load` reads it, but a key repeated in one mapping
    raises `yaml.YAMLError` (a ConstructorError whose `problem_mark` is the second key)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


__all__ = ["load_yaml_text"]
