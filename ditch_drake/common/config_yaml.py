"""Config dataclasses to and from YAML, with Drake's `yaml_load_typed` and errors that name
the file, the key, its line, the bad value and what was expected."""

import dataclasses
import hashlib
import math
import types
import typing
from pathlib import Path

import yaml
from pydrake.common.yaml import yaml_load_typed

from ditch_drake.common.errors import ConfigError


def load_typed_yaml(path: str | Path, schema: type, what: str):
    """A YAML file read into the dataclass `schema` with Drake's `yaml_load_typed`.

    Raises:
        ConfigError: the file cannot be read, is not UTF-8 YAML, its aliases expand too far
            (`compose_yaml`), or it has unknown keys or wrong types (a typo'd key is an error,
            not ignored); the message names `what` and the file.
    """
    path = Path(path)
    text = read_yaml_text(path, what)
    root = compose_yaml(text, f"{what} {path}")
    if root is None:
        raise ConfigError(f"{what} {path} is empty; expected a mapping of {schema.__name__}'s fields")
    _check_node(root, schema, f"{what} {path}", "")
    try:
        return yaml_load_typed(schema=schema, data=text)
    except (RuntimeError, ValueError, TypeError, AssertionError) as error:
        raise ConfigError(f"invalid {what} {path}: {error}") from error


def read_yaml_text(path: str | Path, what: str) -> str:
    """The text of a user's YAML file.

    Raises:
        ConfigError: the file cannot be read or is not UTF-8, naming `what` and the file.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise ConfigError(f"cannot read {what} {path}: {error}") from error
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ConfigError(f"{what} {path}: byte {error.start} is not UTF-8 ({error.reason}); expected UTF-8 "
                          "text") from error


# How many nodes a YAML text's aliases may add when expanded. Every loader expands them: the
# schema check below walks each alias's subtree, `yaml_load_typed` copies it, and each copied
# environment or task is then validated. Nested aliases multiply, so a file of a few kB can
# stand for 10^9 nodes and hang a command for hours. The limit refuses that in milliseconds
# while leaving anchors usable for what people share with them (a controller config, a
# terrain, a list of tasks: hundreds of nodes); a file without aliases is never limited.
MAX_ALIAS_NODES = 100_000


def compose_yaml(text: str, where: str):
    """The node graph of a user's YAML text (None for an empty one), composed by PyYAML's
    SafeLoader, whose aliases share their anchor's node.

    Raises:
        ConfigError: malformed YAML, nesting deeper than Python's recursion allows, an alias
            inside its own anchor, or aliases that expand to more than `MAX_ALIAS_NODES` nodes
            beyond the text's own, naming `where`.
    """
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as error:
        raise ConfigError(f"malformed YAML in {where}: {error}") from error
    except RecursionError as error:
        raise ConfigError(f"{where}: YAML nested too deeply to read; expected a config file") from error
    if root is not None:
        distinct, expanded = _node_counts(root, where)
        if expanded - distinct > MAX_ALIAS_NODES:
            raise ConfigError(f"{where}: its aliases (*name) expand to {expanded:,} nodes, {expanded - distinct:,} "
                              f"more than the text's own {distinct:,}; expected at most {MAX_ALIAS_NODES:,} more "
                              "(write the repeated part out, or alias less of it)")
    return root


def safe_load_yaml(text: str, where: str):
    """`yaml.safe_load` of a text that may come from a user, after `compose_yaml`'s checks.

    Raises:
        ConfigError: as `compose_yaml`, naming `where`.
    """
    compose_yaml(text, where)
    return yaml.safe_load(text)


def _node_counts(root, where: str) -> tuple[int, int]:
    """(distinct nodes, nodes once every alias is expanded) of a composed YAML graph.

    Each node's expanded size is counted once and reused wherever an alias repeats it, so
    this takes time in the distinct nodes, not in the expansion. Iterative: a deep text
    must not exhaust Python's stack here either.
    """
    size: dict[int, int] = {}
    in_progress: set[int] = set()
    stack = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if children_done:
            size[key] = 1 + sum(size[id(child)] for child in _children(node))
            in_progress.discard(key)
            continue
        if key in size:
            continue
        if key in in_progress:
            raise ConfigError(f"{where}: an alias (*name) at line {node.start_mark.line + 1} refers to a node that "
                              "contains it; expected no recursive aliases")
        in_progress.add(key)
        stack.append((node, True))
        for child in _children(node):
            if id(child) in in_progress:
                raise ConfigError(f"{where}: an alias (*name) at line {node.start_mark.line + 1} refers to a node "
                                  "that contains it; expected no recursive aliases")
            if id(child) not in size:
                stack.append((child, False))
    return len(size), size[id(root)]


def _children(node) -> list:
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


_SCALAR_TAGS = {int: ("int",), float: ("int", "float"), bool: ("bool",), str: ("str", "int", "float", "bool")}


def _check_node(node, schema, where: str, key: str) -> None:
    """Raises ConfigError naming the key, its line, the bad value and the expected type, for a
    YAML node that does not fit `schema` (a dataclass, a scalar type, list, dict or Optional).
    Types it does not know are left to `yaml_load_typed`."""
    line = node.start_mark.line + 1
    name = key or "the top level"
    origin, arguments = typing.get_origin(schema), typing.get_args(schema)
    if origin in (typing.Union, types.UnionType):
        if node.tag == "tag:yaml.org,2002:null" and type(None) in arguments:
            return
        options = [argument for argument in arguments if argument is not type(None)]
        if node.tag.startswith("!"):  # A variant named by its YAML tag, as Drake writes them.
            named = [option for option in options if getattr(option, "__name__", None) == node.tag[1:]]
            if named:
                _check_node(node, named[0], where, key)
            return
        if len(options) == 1 or (options and all(dataclasses.is_dataclass(option) for option in options)):
            _check_node(node, options[0], where, key)  # Untagged: Drake reads the first variant.
        return
    if dataclasses.is_dataclass(schema):
        if not isinstance(node, yaml.MappingNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a mapping of "
                              f"{schema.__name__}'s fields")
        field_types = typing.get_type_hints(schema)
        # A field whose type was set at run time (a union of registered configs) has it on the field.
        field_types.update({f.name: f.type for f in dataclasses.fields(schema) if not isinstance(f.type, str)})
        for key_node, value_node in node.value:
            if key_node.value not in field_types:
                raise ConfigError(f"{where}, line {key_node.start_mark.line + 1}: unknown key "
                                  f"{_join(key, key_node.value)!r}; expected one of {sorted(field_types)}")
            _check_node(value_node, field_types[key_node.value], where, _join(key, key_node.value))
        return
    if origin is list:
        if not isinstance(node, yaml.SequenceNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a list")
        for index, item in enumerate(node.value):
            _check_node(item, arguments[0] if arguments else typing.Any, where, f"{key}[{index}]")
        return
    if origin is dict:
        if not isinstance(node, yaml.MappingNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a mapping")
        for key_node, value_node in node.value:
            _check_node(value_node, arguments[1] if arguments else typing.Any, where, _join(key, key_node.value))
        return
    if schema in _SCALAR_TAGS:
        tag = node.tag.rsplit(":", 1)[-1] if isinstance(node, yaml.ScalarNode) else None
        if tag not in _SCALAR_TAGS[schema]:
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected {schema.__name__}"
                              + _float_hint(node, schema))


def _float_hint(node, schema) -> str:
    """Why a number was read as a string, where YAML 1.1 (PyYAML's, and so the check's) took
    it for one: its floats need a dot and a signed exponent, so 1e308 is the string "1e308"."""
    if schema is not float or not isinstance(node, yaml.ScalarNode) or node.tag != "tag:yaml.org,2002:str":
        return ""
    if node.style is not None:  # Quoted: a string on purpose.
        return ""
    try:
        value = float(node.value)
    except ValueError:
        return ""
    if math.isnan(value):
        written = ".nan"
    elif math.isinf(value):
        written = ".inf" if value > 0 else "-.inf"
    else:
        mantissa, _, exponent = node.value.replace("_", "").lower().partition("e")
        if "." not in mantissa:
            mantissa += ".0"
        if exponent and exponent[0] not in "+-":
            exponent = "+" + exponent
        written = mantissa + (f"e{exponent}" if exponent else "")
    return f" ({node.value} is read by YAML as a string; write {written})"


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


def _describe(node) -> str:
    if isinstance(node, yaml.ScalarNode):
        return f"{node.value!r} ({node.tag.rsplit(':', 1)[-1]})"
    return "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"


# The metadata of a field added to a config after rollouts of it were recorded, as in
# `field(default=0.0, metadata=WRITTEN_WHEN_SET)`: `to_plain` (so `config_to_yaml`) leaves it
# out where it holds its default, so that a config that does not use it keeps the text and the
# `config_digest` (part of every recorded rollout's key) it had before the field existed.
WRITTEN_WHEN_SET = types.MappingProxyType({"written_when_set": True})


def _written(config, f: dataclasses.Field) -> bool:
    """Whether `to_plain` writes field `f` of the dataclass `config` (see `WRITTEN_WHEN_SET`)."""
    if not f.metadata.get("written_when_set"):
        return True
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    return getattr(config, f.name) != default


def to_plain(value):
    """A dataclass (or a value inside one) as plain YAML types: lists for tuples, None kept,
    inf and nan as floats (YAML .inf, .nan, which read back); fields marked
    `WRITTEN_WHEN_SET` only where they differ from their default."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value) if _written(value, f)}
    if isinstance(value, (list, tuple)):
        return [to_plain(item) for item in value]
    if isinstance(value, dict):
        return {str(key): to_plain(item) for key, item in value.items()}
    return value


def config_to_yaml(config) -> str:
    """`config`'s fields as a YAML mapping (every field written, None as null)."""
    return yaml.safe_dump(to_plain(config), sort_keys=False, default_flow_style=None, width=1000)


def config_from_yaml(schema: type, text: str, where: str = "config"):
    """The `schema` instance of `config_to_yaml`'s text.

    Raises:
        ConfigError: the text does not fit `schema`, naming `where` and the key.
    """
    root = compose_yaml(text, where)
    if root is not None:
        _check_node(root, schema, where, "")
    try:
        return yaml_load_typed(schema=schema, data=text or "{}")
    except (RuntimeError, ValueError, TypeError, AssertionError) as error:
        raise ConfigError(f"invalid {where}: {error}") from error


def type_path(kind: type) -> str:
    """"module:QualifiedName" of a class, which `importlib` can find again."""
    return f"{kind.__module__}:{kind.__qualname__}"


def config_digest(config) -> str:
    """First 16 hex digits of the SHA-256 of a config's type and fields: equal configs, equal digests."""
    text = type_path(type(config)) + "\n" + config_to_yaml(config)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
