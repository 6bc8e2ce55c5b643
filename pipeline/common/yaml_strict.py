"""YAML that refuses a key given twice in one mapping (two tasks with one name), instead of keeping the
last one silently."""

from __future__ import annotations

from pathlib import Path

import yaml

from pipeline.common.errors import PipelineInputError


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key twice in one mapping (two tasks with one name)."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False):
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise PipelineInputError(
                loader.name, str(key),
                f"duplicate key (line {seen[key] + 1} and line {key_node.start_mark.line + 1}): "
                "two entries with one name")
        seen[key] = key_node.start_mark.line
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml_strict(path: str | Path):
    """YAML without silently-overwritten duplicate keys."""
    path = Path(path)
    text = path.read_text()
    loader = _StrictLoader(text)
    loader.name = str(path)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()
