"""Small XML helpers shared by the FEBio writers (element building, provenance comment, pretty text)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from ..errors import HbmError
from .febio_tags import check_tree


def sub(parent: ET.Element, tag: str, text=None, **attrs) -> ET.Element:
    """Child element; numbers written with 10 significant digits."""
    el = ET.SubElement(parent, tag, {k.rstrip("_"): str(v) for k, v in attrs.items()})
    if text is not None:
        el.text = f"{text:.10g}" if isinstance(text, float) else str(text)
    return el


def vec(v) -> str:
    return ",".join(f"{x + 0.0:.10g}" for x in v)  # + 0.0: no "-0"


def to_text(root: ET.Element, header_lines: list[str]) -> str:
    """Checked (every name in the pinned FEBio table) and indented XML text with a comment header."""
    bad = check_tree(root)
    if bad:  # a writer bug, not a user error: refuse to write a card FEBio would reject
        raise HbmError("FEBio card uses names not in the pinned FEBio table: " + "; ".join(bad))
    ET.indent(root)
    comment = "\n".join("  " + line.replace("--", "- -") for line in header_lines)
    return f'<?xml version="1.0" encoding="UTF-8"?>\n<!--\n{comment}\n-->\n' + ET.tostring(root, encoding="unicode") + "\n"


def provenance_lines(src, card_name: str, valid: str, checks) -> list[str]:
    """Comment lines: provenance, validity and the verification numbers."""
    lines = [f"hbm export: {card_name}"]
    lines += [f"{k}: {v}" for k, v in src.provenance().items()]
    lines += [f"valid for: {valid}", "material axis (muscle fibres): global x"]
    for c in checks:
        lines.append(f"check ({c.method}): max relative difference to hbm {c.error_tested:.3g} on the tested range, "
                     f"{c.error_extended:.3g} on 1.5x it; {'exact card, tolerance' if c.exact else 'stated bound'} "
                     f"{c.bound:.3g}: {'passed' if c.passed else 'FAILED'}")
    lines += src.notes
    return lines
