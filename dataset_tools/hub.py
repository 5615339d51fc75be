"""`bcrl-hub push|pull`: share LeRobot datasets and policy checkpoints through a Hugging Face hub.

The endpoint comes from `HF_ENDPOINT` (huggingface.co by default, or any hub-compatible server such as
`bcrl-local-hub`), the token from the usual place (`HF_TOKEN` or `hf auth login`). Examples:
    bcrl-hub push --kind=dataset --repo_id=me/lift_sigma0.1 --root=data/lift_sigma0.1 --private=true
    bcrl-hub pull --kind=dataset --repo_id=me/lift_sigma0.1 --root=data/pulled --revision=v3.0
    bcrl-hub push --kind=policy --repo_id=me/bcrl_lift --root=outputs/train/x/checkpoints/last/pretrained_model
    bcrl-hub pull --kind=policy --repo_id=me/bcrl_lift --root=policies/bcrl_lift
A pull downloads into a hidden folder next to `--root`, checks every file against the hub's hashes and
only then moves it into place; an interrupted pull keeps the files it completed there, and the same
command resumes with the missing ones (huggingface_hub 1.33 restarts a file cut off half-way from zero).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import draccus
from huggingface_hub.errors import HfHubHTTPError, RepositoryNotFoundError

from dataset_tools.local_hub import git_blob_oid
from dataset_tools.noise import DemonstratorConfig
from dataset_tools.summary import summarize
from dataset_tools.writer import default_root, read_bcrl_meta

PICKLE_SUFFIXES = (".bin", ".pt", ".pth", ".pkl", ".pickle", ".ckpt")
POLICY_FILE_PATTERNS = ["*.json", "*.safetensors", "*.md"]
DEFAULT_ENDPOINT = "https://huggingface.co"


class HubError(RuntimeError):
    """A push or pull that must stop; the message says what and where."""


@dataclass
class PushConfig:
    kind: str = "dataset"  # "dataset" (a LeRobotDataset v3 folder) or "policy" (a pretrained_model folder)
    repo_id: str = ""  # the hub repository, e.g. "me/lift_sigma0.1"
    root: Path | None = None  # local folder to push; datasets default to $HF_LEROBOT_HOME/<repo_id>
    private: bool = False
    branch: str | None = None  # push to this branch (created if missing) instead of main
    tag_version: bool = True  # datasets: tag the commit "v3.0" so LeRobot resolves the codebase version


@dataclass
class PullConfig:
    kind: str = "dataset"
    repo_id: str = ""
    root: Path | None = None  # destination; datasets default to $HF_LEROBOT_HOME/<repo_id>
    revision: str | None = None  # branch, tag or commit; default: the "v3.0" tag for datasets if any, else main
    overwrite: bool = False  # replace an existing folder at root


def configure_hub() -> str:
    """Point huggingface_hub at `HF_ENDPOINT` now (its constants are read at import) and allow the network."""
    from huggingface_hub import constants

    endpoint = os.environ.get("HF_ENDPOINT", DEFAULT_ENDPOINT).rstrip("/")
    constants.ENDPOINT = endpoint
    constants.HUGGINGFACE_CO_URL_TEMPLATE = endpoint + "/{repo_id}/resolve/{revision}/{filename}"
    # bcrl-hub exists to talk to the hub: a global HF_HUB_OFFLINE (our Makefile sets it) must not stop it.
    constants.HF_HUB_OFFLINE = False
    if "huggingface.co" not in endpoint:
        if "HF_HUB_DISABLE_XET" not in os.environ:
            constants.HF_HUB_DISABLE_XET = True  # other hub servers speak plain LFS, not Xet storage
        # RepoCard.validate posts to a hard-coded https://huggingface.co/api/validate-yaml whatever the
        # endpoint (huggingface_hub 1.33), which a private or offline hub cannot reach: skip it there.
        from huggingface_hub import repocard

        repocard.RepoCard.validate = lambda self, repo_type=None: None
    return endpoint


def _repo_type(kind: str) -> str:
    if kind not in ("dataset", "policy"):
        raise HubError(f"--kind must be 'dataset' or 'policy', got {kind!r}")
    return "dataset" if kind == "dataset" else "model"


def _require_repo_id(repo_id: str) -> None:
    if not repo_id or repo_id.count("/") != 1:
        raise HubError(f"--repo_id must look like 'owner/name', got {repo_id!r}")


# -- cards -------------------------------------------------------------------------------------------
def dataset_description(root: Path) -> str:
    """Markdown for the dataset card: demonstrators, fps, action layout and the command that made it."""
    summary = summarize(root)
    meta = read_bcrl_meta(root)
    lines = [
        "Made with [lerobot-bcrl](https://github.com/) for BC+RL from non-optimal demonstrations.",
        "",
        f"- **Source:** {meta.get('source', 'unknown')}",
        f"- **Episodes / frames:** {summary['episodes']} / {summary['frames']} at **{summary['fps']} fps**"
        " (the rate a policy trained on it must run at)",
        f"- **Action layout:** `{meta.get('action_layout', 'see meta/info.json')}`",
    ]
    if "success_rate" in summary:
        lines.append(
            f"- **Demonstrators' success / return:** {summary['success_rate']:.0%} / "
            f"{summary['mean_return']:.1f} +/- {summary['return_ci95']:.1f} (95 % CI)"
        )
    plain_expert = asdict(DemonstratorConfig())
    for i, d in enumerate(meta.get("demonstrators", [])):
        # the skill knobs this operator sets away from the plain expert's (its noise has its own words)
        knobs = ", ".join(f"{k} = {v}" for k, v in d.items() if not k.startswith("noise_") and v != plain_expert.get(k))
        lines.append(
            f"- **Demonstrator {i}:** noise sigma = {d['noise_std']}, mean = {d['noise_mean']}, "
            f"correlation = {d['noise_correlation']}" + (f"; {knobs}" if knobs else "")
        )
    if meta.get("command"):
        lines += ["", "Made by:", "", "```bash", meta["command"], "```"]
    return "\n".join(lines)


def policy_card(root: Path, repo_id: str) -> str:
    config = json.loads((root / "config.json").read_text())
    train_config = root / "train_config.json"
    dataset = json.loads(train_config.read_text()).get("dataset", {}).get("repo_id") if train_config.exists() else None
    return "\n".join(
        [
            "---",
            "library_name: lerobot",
            "tags: [lerobot, bcrl, robotics]",
            "---",
            f"# {repo_id}",
            "",
            f"A `{config.get('type')}` policy from lerobot-bcrl (BC+RL). Load it with LeRobot:",
            "",
            "```bash",
            f"lerobot-eval --policy.path={repo_id} --env.type=bcrl_lift",
            "```",
            "",
            f"- Trained on: `{dataset}`" if dataset else "- Training dataset: not recorded",
            "- Weights: safetensors only.",
        ]
    )


# -- push --------------------------------------------------------------------------------------------
def push(cfg: PushConfig) -> str:
    """Push a dataset or policy folder; returns the URL of the commit."""
    configure_hub()
    from huggingface_hub import HfApi

    _require_repo_id(cfg.repo_id)
    repo_type = _repo_type(cfg.kind)
    if cfg.kind == "dataset":
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        root = Path(cfg.root) if cfg.root is not None else default_root(cfg.repo_id)
        dataset = LeRobotDataset(cfg.repo_id, root=root)
        dataset.push_to_hub(
            branch=cfg.branch,
            tags=["bcrl", "lerobot-bcrl"],
            license="apache-2.0",
            tag_version=cfg.tag_version,
            private=cfg.private,
            dataset_description=dataset_description(root),
        )
    else:
        if cfg.root is None:
            raise HubError("--root must be the policy's pretrained_model folder")
        root = Path(cfg.root)
        check_policy_folder(root)
        api = HfApi()
        api.create_repo(cfg.repo_id, repo_type=repo_type, private=cfg.private, exist_ok=True)
        if cfg.branch:
            api.create_branch(cfg.repo_id, branch=cfg.branch, repo_type=repo_type, exist_ok=True)
        api.upload_folder(
            folder_path=root,
            repo_id=cfg.repo_id,
            repo_type=repo_type,
            revision=cfg.branch,
            allow_patterns=[p for p in POLICY_FILE_PATTERNS if p != "*.md"],
            commit_message="Upload policy with bcrl-hub",
        )
        api.upload_file(
            path_or_fileobj=policy_card(root, cfg.repo_id).encode(),
            path_in_repo="README.md",
            repo_id=cfg.repo_id,
            repo_type=repo_type,
            revision=cfg.branch,
        )
    api = HfApi()
    sha = api.repo_info(cfg.repo_id, repo_type=repo_type, revision=cfg.branch).sha
    return f"{os.environ.get('HF_ENDPOINT', DEFAULT_ENDPOINT)}/{'datasets/' if cfg.kind == 'dataset' else ''}{cfg.repo_id} @ {sha}"


# -- pull --------------------------------------------------------------------------------------------
def _default_revision(api, repo_id: str, repo_type: str) -> str:
    if repo_type == "dataset":
        from lerobot.datasets.dataset_metadata import CODEBASE_VERSION

        tags = {t.name for t in api.list_repo_refs(repo_id, repo_type=repo_type).tags}
        if CODEBASE_VERSION in tags:
            return CODEBASE_VERSION
    return "main"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def verify_download(folder: Path, entries) -> None:
    """Compare every downloaded file with the hub's hashes; a bad file is deleted so a retry fetches it."""
    for entry in entries:
        if not hasattr(entry, "blob_id"):
            continue  # a folder
        local = folder / entry.path
        if not local.is_file():
            raise HubError(f"{entry.path}: missing after download")
        if entry.lfs is not None:
            actual, expected = _sha256(local), entry.lfs.sha256
        else:
            actual, expected = git_blob_oid(local.read_bytes()), entry.blob_id
        if actual != expected or local.stat().st_size != entry.size:
            local.unlink()
            for stale in (folder / ".cache" / "huggingface" / "download").glob(f"{entry.path}.*"):
                stale.unlink()
            raise HubError(
                f"{entry.path}: corrupted download (hash {actual[:12]}, hub says {expected[:12]}); "
                "it was deleted, run the same command again to fetch it anew"
            )


def check_policy_folder(folder: Path) -> None:
    """Safetensors only, and a config LeRobot knows completely: never run what we cannot read safely."""
    folder = Path(folder)
    pickles = sorted(p.name for p in folder.rglob("*") if p.suffix in PICKLE_SUFFIXES)
    if pickles:
        raise HubError(f"{folder}: refusing pickle files {pickles}; policies are exchanged as safetensors only")
    if not (folder / "model.safetensors").is_file():
        raise HubError(f"{folder}: no model.safetensors")
    config_path = folder / "config.json"
    if not config_path.is_file():
        raise HubError(f"{folder}: no config.json")
    config = json.loads(config_path.read_text())
    import lerobot_bcrl  # noqa: F401  (registers our policy type)
    from lerobot.configs.policies import PreTrainedConfig

    policy_type = config.get("type")
    if policy_type not in PreTrainedConfig.get_known_choices():
        raise HubError(f"{config_path}: unknown policy type {policy_type!r}")
    known = {f.name for f in fields(PreTrainedConfig.get_choice_class(policy_type))} | {"type"}
    unknown = sorted(set(config) - known)
    if unknown:
        raise HubError(
            f"{config_path}: unknown config keys {unknown} for policy type {policy_type!r}; refusing to load a "
            "policy this version cannot interpret (update lerobot-bcrl, or fix the checkpoint)"
        )


def pull(cfg: PullConfig) -> Path:
    configure_hub()
    from huggingface_hub import HfApi, snapshot_download

    _require_repo_id(cfg.repo_id)
    repo_type = _repo_type(cfg.kind)
    if cfg.root is not None:
        root = Path(cfg.root)
    elif cfg.kind == "dataset":
        root = default_root(cfg.repo_id)
    else:
        raise HubError("--root is required for policies")
    if root.exists() and not cfg.overwrite:
        raise HubError(f"{root} already exists; pass --overwrite=true to replace it")
    api = HfApi()
    revision = cfg.revision or _default_revision(api, cfg.repo_id, repo_type)
    sha = api.repo_info(cfg.repo_id, repo_type=repo_type, revision=revision).sha  # pin one commit
    staging = root.parent / f".{root.name}.pulling"
    staging.parent.mkdir(parents=True, exist_ok=True)
    try:
        snapshot_download(cfg.repo_id, repo_type=repo_type, revision=sha, local_dir=staging)
        verify_download(staging, api.list_repo_tree(cfg.repo_id, repo_type=repo_type, revision=sha, recursive=True))
    except HubError:
        raise
    except Exception as e:
        raise HubError(
            f"pull of {cfg.repo_id}@{revision} failed: {type(e).__name__}: {e}. Partial files are kept in "
            f"{staging}; run the same command again to resume."
        ) from e
    if cfg.kind == "policy":
        try:
            check_policy_folder(staging)
        except HubError:
            shutil.rmtree(staging)  # refused: keep nothing of it
            raise
    shutil.rmtree(staging / ".cache", ignore_errors=True)
    if root.exists():
        shutil.rmtree(root)
    os.replace(staging, root)
    return root


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    usage = "usage: bcrl-hub push|pull --kind=dataset|policy --repo_id=owner/name --root=DIR [...]"
    if argv[:1] in (["-h"], ["--help"]):
        print(f"{usage}\n\n{__doc__}\nEach command's options: bcrl-hub push --help, bcrl-hub pull --help")
        return
    if not argv or argv[0] not in ("push", "pull"):
        print(usage, file=sys.stderr)
        raise SystemExit(2)
    action, rest = argv[0], argv[1:]
    try:
        if action == "push":
            cfg = draccus.parse(PushConfig, args=rest, prog="bcrl-hub push")
            print(f"pushed {cfg.kind} {cfg.root or default_root(cfg.repo_id)} -> {push(cfg)}")
        else:
            cfg = draccus.parse(PullConfig, args=rest, prog="bcrl-hub pull")
            print(f"pulled {cfg.kind} {cfg.repo_id} -> {pull(cfg)}")
    except HubError as e:
        print(f"bcrl-hub: error: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    except HfHubHTTPError as e:
        endpoint = os.environ.get("HF_ENDPOINT", DEFAULT_ENDPOINT)
        hint = " (a private repo needs a token: HF_TOKEN or `hf auth login`)" if isinstance(e, RepositoryNotFoundError) else ""
        print(f"bcrl-hub: error: {type(e).__name__} from {endpoint}: {str(e).splitlines()[0]}{hint}", file=sys.stderr)
        raise SystemExit(1) from None


if __name__ == "__main__":
    main()
