"""One escaper per target language: the only way text from a file reaches an
artefact (docs/security.md).

Every string that comes from an input file (serial, plan name, segment
labels, method, command line, units, parameter names, notes) is untrusted.
A generated artefact embeds it only through the function for its language:

- C: ``c_identifier`` validates a name from the command line (``--prefix``);
  free text goes only into a string literal (``c_string``) in which every
  byte outside printable ASCII, and every quote, backslash and ``?`` (a
  trigraph ``??/`` is a backslash in C99), is an octal escape. Comments hold
  only text the tool writes itself, or a word ``c_comment_word`` accepts
  (no ``*``, ``/*``, ``\\``, ``?``, newline: nothing that closes a comment,
  splices a line or forms a trigraph).
- JSON: ``json_text`` (the json module, ASCII only).
- YAML: ``yaml_string``/``yaml_key``/``yaml_number``: double-quoted scalars
  in which everything outside printable ASCII is a YAML escape, so any YAML
  1.1 or 1.2 reader gets back the same string (anchors ``&a``, aliases
  ``*a``, tags, ``#`` and ``:`` are inert inside double quotes); keys that a
  YAML 1.1 reader would turn into booleans or null are quoted.
- CSV: ``csv_text`` (the csv module), with ``csv_cell`` neutralising a text
  cell a spreadsheet would run as a formula (leading ``=``, ``+``, ``-``,
  ``@``, tab, CR: a ``'`` is put in front, as OWASP recommends).
- Markdown: ``md_text`` escapes HTML (``&``, ``<``, ``>`` become entities)
  and the characters that start Markdown syntax, and shows control
  characters as ``\\xNN``: the text renders as the same text, never as a tag,
  link, image, heading or list.
- HTML: ``html_text`` (html.escape, quotes included, control characters
  shown as ``\\xNN``).
- Matplotlib labels: ``mpl_text`` (``$`` would start mathtext).
- A plain error line: ``line_text`` (control characters shown as ``\\xNN``:
  the line stays one line and sends no escape sequence).
- The terminal (rich): ``term_text`` (rich markup escaped, so ``[/]`` neither
  styles nor crashes; escape sequences and other control characters shown as
  ``\\xNN``, so a file cannot move the cursor or retitle the terminal).
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import re

# --------------------------------------------------------------------------- C

C_IDENTIFIER = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}")
C_KEYWORDS = frozenset("""auto break case char const continue default do double else enum
extern float for goto if inline int long register restrict return short signed sizeof static
struct switch typedef union unsigned void volatile while _Bool _Complex _Imaginary""".split())


def c_identifier(name: str, what: str = "name") -> str:
    """``name`` if it is a safe C identifier (a letter, then letters, digits,
    underscores; at most 32 characters; not a keyword), else ValueError."""
    if not isinstance(name, str) or not C_IDENTIFIER.fullmatch(name) or name in C_KEYWORDS:
        raise ValueError(f"{what} {name!r} is not a C identifier (a letter, then letters, "
                         "digits or '_', at most 32 characters)")
    return name


def _c_byte(b: int) -> str:
    if 0x20 <= b < 0x7F and b not in (0x22, 0x27, 0x5C, 0x3F):  # " ' \ ?
        return chr(b)
    return "\\%03o" % b  # octal takes at most 3 digits: never swallows what follows


def c_string(text) -> str:
    """A C string literal (with its quotes) holding exactly the UTF-8 bytes of
    ``text``; nothing in ``text`` can end the literal or the line, form a
    trigraph, or look like a comment marker."""
    data = str(text).encode("utf-8", "surrogatepass")
    out = []
    for i, b in enumerate(data):
        nxt = data[i + 1] if i + 1 < len(data) else None
        if (b, nxt) in ((0x2A, 0x2F), (0x2F, 0x2A)):  # "*/" and "/*": inert here, but
            out.append("\\%03o" % b)                 # no comment marker even so
        else:
            out.append(_c_byte(b))
    return '"' + "".join(out) + '"'


_C_COMMENT_WORD = re.compile(r"[A-Za-z0-9 ^()._+-]{1,40}(/[A-Za-z0-9 ^()._+-]{1,40})*")


def c_comment_word(text) -> str | None:
    """``text`` if it may appear in a C comment as it is (letters, digits,
    `` ^()._+-`` and single ``/`` between them: no ``*``, no ``//``, no
    ``\\``, no ``?``, no newline), else None."""
    s = str(text)
    return s if _C_COMMENT_WORD.fullmatch(s) else None


# ------------------------------------------------------------------------ JSON


def json_text(obj, indent: int | None = 2) -> str:
    """JSON through the json module (ASCII output, no NaN)."""
    return json.dumps(obj, indent=indent, ensure_ascii=True, allow_nan=False)


# ------------------------------------------------------------------------ YAML

_YAML_PLAIN_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# plain words that YAML 1.1 (PyYAML and friends) reads as booleans or null
_YAML_RESERVED = frozenset("y n yes no true false on off null".split())
_YAML_ESC = {0x00: "\\0", 0x07: "\\a", 0x08: "\\b", 0x09: "\\t", 0x0A: "\\n", 0x0B: "\\v",
             0x0C: "\\f", 0x0D: "\\r", 0x1B: "\\e", 0x22: '\\"', 0x5C: "\\\\"}


def _yaml_char(c: str) -> str:
    o = ord(c)
    if o in _YAML_ESC:
        return _YAML_ESC[o]
    if 0x20 <= o < 0x7F:
        return c
    if o < 0x100:
        return "\\x%02x" % o
    if o < 0x10000:
        return "\\u%04x" % o
    return "\\U%08x" % o


def yaml_string(text) -> str:
    """A YAML double-quoted scalar that every reader loads as ``text``."""
    return '"' + "".join(_yaml_char(c) for c in str(text)) + '"'


def yaml_key(key) -> str:
    k = str(key)
    if _YAML_PLAIN_KEY.fullmatch(k) and k.lower() not in _YAML_RESERVED:
        return k
    return yaml_string(k)


def yaml_number(x) -> str:
    """A number that YAML 1.1 and 1.2 readers (and JSON) load as the same
    float: repr (exact round trip) with a '.' before any exponent, as YAML 1.1
    requires (``1e-05`` would be a string there, ``1.0e-05`` is a float)."""
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int):
        return str(x)
    x = float(x)
    if not math.isfinite(x):
        return "null"
    s = repr(x)
    if "e" in s and "." not in s:
        m, e = s.split("e")
        s = f"{m}.0e{e}"
    return s


def yaml_scalar(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, (bool, int, float)):
        return yaml_number(v)
    return yaml_string(v)


# ------------------------------------------------------------------------- CSV

_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(text) -> str:
    """A text cell a spreadsheet shows as text: a leading formula character
    gets a ``'`` in front (a plain number or a lone ``-`` is left alone)."""
    s = str(text)
    if len(s) > 1 and s.startswith(_FORMULA_START):
        try:
            float(s)
        except ValueError:
            return "'" + s
    return s


def csv_text(rows) -> str:
    """Rows (lists of cells) as CSV through the csv module: a cell holding a
    comma, a quote or a newline is quoted, so every row reads back as itself."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


# -------------------------------------------------------------------- Markdown

_CTRL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")
_MD_SPECIAL = re.compile(r"([\\`*|~])|(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])|\](?=[(\[])")


def _show_ctrl(s: str) -> str:
    """Tabs become spaces; every other control character (newlines included)
    is shown as the text \\xNN (\\uNNNN for the two Unicode line breaks)."""
    s = s.replace("\t", " ")
    return _CTRL.sub(lambda m: "\\x%02x" % ord(m.group()) if ord(m.group()) < 0x100
                     else "\\u%04x" % ord(m.group()), s)


_MD_BLOCK_START = re.compile(r"^(?:[-+](?=\s|$|-)|#{1,6}(?=\s|$)|=+\s*$|\[)")
_MD_ORDERED = re.compile(r"^(\d{1,9})([.)])(?=\s|$)")


def md_text(text, block: bool = True) -> str:
    """Markdown that renders as ``text``: no raw HTML (``& < >`` become
    entities); no code span, emphasis, table cell break, link or image (``\\ ` *
    | ~``, a ``_`` that is not inside a word, and a ``]`` before ``(`` or ``[``
    are backslash-escaped); newlines and other control characters are shown as
    ``\\xNN``. ``block``: the text starts a line (a paragraph, a heading, a
    list item), so a leading list, heading or rule marker or a ``[`` (a link
    definition) is escaped too; table cells need not. Plain text
    (``accel_bias[0]``, ``m/s^2``, ``-0.5``) stays as it is."""
    s = html.escape(_show_ctrl(str(text)), quote=False)
    s = _MD_SPECIAL.sub(lambda m: "\\" + m.group(), s)
    s = s.strip(" ")
    if block:
        s = _MD_BLOCK_START.sub(lambda m: "\\" + m.group(), s)
        s = _MD_ORDERED.sub(r"\1\\\2", s)
    return s


# ------------------------------------------------------------------------ HTML


def html_text(text) -> str:
    """Text for an HTML element or attribute (quotes escaped too)."""
    return html.escape(_show_ctrl(str(text)), quote=True)


# ------------------------------------------------------------------ matplotlib


def mpl_text(text) -> str:
    """A label matplotlib draws as it is (``$`` would start mathtext)."""
    return _show_ctrl(str(text)).replace("$", r"\$")


# -------------------------------------------------------------- terminal (rich)


def term_text(text) -> str:
    """Text for a rich console or table: markup and control characters inert."""
    from rich.markup import escape as rich_escape

    return rich_escape(_show_ctrl(str(text)))


def line_text(text) -> str:
    """File text for a plain one-line message (an error line on stderr)."""
    return _show_ctrl(str(text))
