"""A small, safe XML reader and writer for URDF files.

Built on expat directly (the parser behind ``xml.etree``) so that every element knows its line, and so
that a hostile file cannot hang or exhaust memory: a document type declaration (where entities are
declared: billion laughs, quadratic blow-up, external entities) is refused outright, as is a file larger
than ``MAX_BYTES``. What is kept is the element tree with attributes, text and comments, enough to write
the document back with a few attributes changed."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from xml.parsers import expat
from xml.sax.saxutils import escape, quoteattr

MAX_BYTES = 32 * 1024 * 1024  # a URDF is text; meshes live in their own files


class XMLFileError(ValueError):
    """Unreadable or refused XML; the message names the file and line."""


@dataclass
class Node:
    tag: str
    attrib: dict[str, str]
    line: int
    children: list = field(default_factory=list)  # Node, str (text) or Comment

    def elements(self, tag: str | None = None) -> list[Node]:
        return [c for c in self.children if isinstance(c, Node) and (tag is None or c.tag == tag)]

    def first(self, tag: str) -> Node | None:
        found = self.elements(tag)
        return found[0] if found else None


@dataclass
class Comment:
    text: str


class _Refused(Exception):
    pass


def parse(data: bytes, where: str) -> Node:
    """The root element of ``data``; ``XMLFileError`` with ``where:LINE: reason`` otherwise."""
    if len(data) > MAX_BYTES:
        raise XMLFileError(f"{where}: {len(data)} bytes is larger than the {MAX_BYTES >> 20} MiB a URDF may be")
    p = expat.ParserCreate()
    p.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    stack: list[Node] = []
    root: list[Node] = []

    def refuse(what: str):
        def handler(*_args):
            raise _Refused(f"{what} are not accepted (entities can make a file expand without bound)")
        return handler

    def start(tag, attrs):
        n = Node(tag, dict(attrs), p.CurrentLineNumber)
        if stack:
            stack[-1].children.append(n)
        else:
            root.append(n)
        stack.append(n)

    def end(_tag):
        stack.pop()

    def text(data_):
        if stack:
            ch = stack[-1].children
            if ch and isinstance(ch[-1], str):
                ch[-1] += data_
            else:
                ch.append(data_)

    def comment(data_):
        if stack:
            stack[-1].children.append(Comment(data_))

    p.StartElementHandler, p.EndElementHandler = start, end
    p.CharacterDataHandler, p.CommentHandler = text, comment
    p.StartDoctypeDeclHandler = refuse("document type declarations (<!DOCTYPE>)")
    p.EntityDeclHandler = refuse("entity declarations")
    p.ExternalEntityRefHandler = refuse("external entities")
    try:
        p.Parse(data, True)
    except _Refused as e:
        raise XMLFileError(f"{where}:{p.CurrentLineNumber}: {e}") from None
    except expat.ExpatError as e:
        raise XMLFileError(f"{where}:{e.lineno}: not well-formed XML ({expat.ErrorString(e.code)})") from None
    if not root:
        raise XMLFileError(f"{where}: no XML element")
    return root[0]


def read(path: str | Path) -> Node:
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise XMLFileError(f"{path}: {size} bytes is larger than the {MAX_BYTES >> 20} MiB a URDF may be")
        data = path.read_bytes()
    except FileNotFoundError:
        raise XMLFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise XMLFileError(f"{path}: is a directory") from None
    except OSError as e:
        raise XMLFileError(f"{path}: cannot read ({e.strerror})") from None
    return parse(data, str(path))


def serialize(node: Node) -> str:
    """The document text of ``node`` (with an XML declaration)."""
    out: list[str] = ['<?xml version="1.0"?>\n']

    def walk(n: Node) -> None:
        attrs = "".join(f" {k}={quoteattr(v)}" for k, v in n.attrib.items())
        if not n.children:
            out.append(f"<{n.tag}{attrs}/>")
            return
        out.append(f"<{n.tag}{attrs}>")
        for c in n.children:
            if isinstance(c, Node):
                walk(c)
            elif isinstance(c, Comment):
                out.append(f"<!--{c.text}-->")
            else:
                out.append(escape(c))
        out.append(f"</{n.tag}>")

    walk(node)
    out.append("\n")
    return "".join(out)
