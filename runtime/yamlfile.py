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


class MalformedYAML(ValueError):
    """Text that is not a YAML document this project reads; the message says where and why
    ("malformed YAML (line 3, column 5): ..."), for the caller to put after the file's name."""


def load_yaml_text(text: str):
    """The document in `text`, as `yaml.safe_load` reads it, except that a key repeated in one
    mapping is refused. Anything the parser cannot hold (a syntax error, a repeated key, an
    integer of thousands of digits, nesting thousands deep) raises MalformedYAML."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(e, "problem", None) or str(e)
        raise MalformedYAML(f"malformed YAML{where}: {problem}") from None
    except ValueError as e:  # an integer of thousands of digits
        raise MalformedYAML(f"malformed YAML: {str(e)[:200]}") from None
    except RecursionError:
        raise MalformedYAML("malformed YAML: nested too deeply") from None


__all__ = ["MalformedYAML", "load_yaml_text"]
