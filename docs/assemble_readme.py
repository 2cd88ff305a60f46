"""Assemble README.md from docs/readme_head.md and the section files in docs/sections/."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ORDER = [
    "io-cli",
    "paper-repro",
    "core-tests",
    "cdpm",
    "sweeps",
    "robust",
    "physics",
    "concealed",
    "development",
]

parts = [(ROOT / "docs" / "readme_head.md").read_text().rstrip() + "\n"]
for name in ORDER:
    path = ROOT / "docs" / "sections" / f"{name}.md"
    if path.exists():
        parts.append(path.read_text().rstrip() + "\n")
(ROOT / "README.md").write_text("\n".join(parts))
print(f"README.md: {sum(p.count(chr(10)) for p in parts)} lines")
