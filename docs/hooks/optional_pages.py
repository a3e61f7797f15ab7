"""MkDocs hook: nav entries for pages that are still being written are kept only while their file exists.

``docs/wrappers.md`` and ``docs/data-and-logging.md`` are listed in ``mkdocs.yml``'s nav before they land;
a nav entry without its file fails ``mkdocs build --strict``, so this drops such an entry (with an INFO
line) until the file is there. Every other nav entry is left to MkDocs' own validation.
"""

import logging
from pathlib import Path

OPTIONAL_PAGES = {"wrappers.md", "data-and-logging.md"}
log = logging.getLogger("mkdocs.hooks.optional_pages")


def _prune(items: list, docs_dir: Path) -> list:
    kept = []
    for item in items:
        title, value = next(iter(item.items())) if isinstance(item, dict) else (None, item)
        if isinstance(value, list):
            value = _prune(value, docs_dir)
            if value:
                kept.append({title: value})
            continue
        if value in OPTIONAL_PAGES and not (docs_dir / value).is_file():
            log.info("nav: %s is not written yet; left out of the nav", value)
            continue
        kept.append(item)
    return kept


def on_config(config):
    if config.nav:
        config.nav = _prune(config.nav, Path(config.docs_dir))
    return config
