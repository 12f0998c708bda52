"""Where a store lives: a local (or shared) folder, or a prefix on object storage (`s3://bucket/prefix`).

A store root is given as text everywhere (command line, flow parameters, task arguments): a path, or a URL whose
scheme fsspec knows (`s3://`; `gs://`, `az://`, `memory://` where their fsspec packages are installed). A URL store
is reached through fsspec (`universal_pathlib`'s `UPath`, so the store's path arithmetic is the same for both) and
shares nothing host-local: no rename, no `flock`, no pid. Credentials and the endpoint come from the environment
as every AWS tool reads them (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_ENDPOINT_URL` for an S3-compatible
server such as MinIO, Ceph or moto; or an AWS profile), so each worker machine needs only those variables.

What object storage gives instead of what a folder gives:
- A PUT is atomic: an object appears whole or not at all (a multipart upload only when it is completed). A file is
  written into a local temporary file and uploaded once, so a writer that fails or is killed uploads nothing.
- A create that must not overwrite (`If-None-Match: *`) and a replace of exactly the version read (`If-Match:
  <ETag>`) are conditional PUTs, which S3 (since 2024), MinIO and moto honour: the store's lock objects and its
  read-modify-write of shard files (a rerun of one utterance) use them (`Store.locked`, `replace_utterance_rows`).
- Listings are never cached (`use_listings_cache=False`): another machine's writes must be seen.
"""

import os
import re
from pathlib import Path

URL = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://(?P<rest>.*)$")

LOCAL_SCHEMES = frozenset({"file", "local"})

StoreRoot = Path | str
"""A store root as the parameters carry it: a local Path, or a URL as text."""


def is_url(root: object) -> bool:
    """Whether `root` names object storage (a URL with a scheme other than `file://`)."""
    if isinstance(root, os.PathLike):
        return False
    match = URL.match(str(root))
    return bool(match) and match["scheme"].lower() not in LOCAL_SCHEMES


def parse_root(root: object) -> StoreRoot:
    """`root` as the flows keep it: a URL stays text (a `Path` would fold its `//`), anything else becomes a Path
    (`file:///x` becomes `/x`)."""
    if isinstance(root, Path):
        return root
    if hasattr(root, "protocol") and hasattr(root, "fs"):   # a UPath (`Store.root` of a URL store)
        return parse_root(str(root))
    text = os.fspath(root) if isinstance(root, os.PathLike) else str(root)
    match = URL.match(text)
    if match and match["scheme"].lower() in LOCAL_SCHEMES:
        return Path("/" + match["rest"].lstrip("/"))
    if match:
        url = text.rstrip("/")
        if not match["rest"].strip("/"):
            raise ValueError(f"{text}: a store on object storage needs a bucket (s3://bucket/prefix)")
        if ".." in url.split("/") or "." in url.split("/")[3:]:
            raise ValueError(f"{text}: a store URL may not hold '.' or '..' segments")
        return url
    return Path(text)


def remote_root(url: str):
    """The fsspec path (`upath.UPath`) of a URL store root; its filesystem caches no listings."""
    try:
        from upath import UPath
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise RuntimeError("a store on object storage needs universal_pathlib and fsspec") from exc
    scheme = URL.match(url)["scheme"].lower()
    options = {"use_listings_cache": False} if scheme in {"s3", "s3a", "gs", "gcs", "az", "abfs"} else {}
    try:
        return UPath(url, **options)
    except (ImportError, ValueError) as exc:
        hint = " (pip install s3fs)" if scheme.startswith("s3") else ""
        raise ValueError(f"{url}: no filesystem for {scheme}:// URLs{hint}: {exc}") from exc


def remote_problem(url: str) -> str | None:
    """Why the store at `url` cannot be used, in one line (no filesystem package, no such bucket, no access, no
    endpoint answering); None when its bucket answers. One request."""
    try:
        root = remote_root(url)
    except (ValueError, RuntimeError) as exc:
        return str(exc)
    bucket = root.path.split("/", 1)[0]
    endpoint = os.environ.get("AWS_ENDPOINT_URL") or os.environ.get("AWS_ENDPOINT_URL_S3") or "AWS"
    try:
        if root.fs.exists(bucket):
            return None
        reason = "does not exist or this machine's credentials may not see it"
    except Exception as exc:   # botocore, aiohttp and fsspec each raise their own kinds
        reason = f"cannot be reached ({type(exc).__name__}: {exc})"
    where = f" at {endpoint}" if root.protocol in ("s3", "s3a") else ""
    return f"cannot use the store {url}: bucket {bucket!r}{where} {reason}"
