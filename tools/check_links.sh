#!/usr/bin/env bash
# Fails if a Markdown file of the repository points outside it or at nothing:
#   - any mention of `../shared` (the documents live in docs/ now);
#   - a relative link or image, inline `[text](path)` or a reference
#     definition `[label]: path`, whose file or directory does not exist;
#   - an anchor `path.md#heading` or `#heading` that names no heading of the
#     target file (GitHub's rule: lower case, punctuation dropped, spaces to
#     hyphens, `-1`, `-2`, ... for repeats).
# Fenced code blocks and inline code are not read. URLs (scheme:...) are not
# fetched. Skips target/, .git/, .venv*/ and node_modules/.
# Usage: bash tools/check_links.sh   (from anywhere; exit 1 on a problem)
set -uo pipefail
export LC_ALL=C.UTF-8

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root" || exit 2

problems=0
report() {
    echo "$1: $2" >&2
    problems=$((problems + 1))
}

# The text of a Markdown file without fenced code blocks and inline code.
prose() {
    sed -e '/^[[:space:]]*```/,/^[[:space:]]*```/d' \
        -e '/^[[:space:]]*~~~/,/^[[:space:]]*~~~/d' \
        -e 's/``[^`]*``//g' -e 's/`[^`]*`//g' "$1"
}

# The anchors of a Markdown file's headings, one per line.
anchors() {
    declare -A seen=()
    local slug
    while IFS= read -r slug; do
        if [[ -n ${seen[$slug]+x} ]]; then
            seen[$slug]=$((seen[$slug] + 1))
            echo "$slug-${seen[$slug]}"
        else
            seen[$slug]=0
            echo "$slug"
        fi
    done < <(prose "$1" | sed -n 's/^#\{1,6\}[[:space:]]\{1,\}//p' |
        sed -e 's/[[:space:]]*#*[[:space:]]*$//' -e 's/.*/\L&/' \
            -e 's/[^[:alnum:] _-]//g' -e 's/ /-/g')
}

mapfile -t files < <(find . \( -name target -o -name .git -o -name 'node_modules' \
    -o -name '.venv*' \) -prune -o -type f -name '*.md' -print | sed 's|^\./||' | sort)

for file in "${files[@]}"; do
    if grep -n '\.\./shared' "$file" >/dev/null; then
        while IFS= read -r hit; do
            report "$file:${hit%%:*}" "points outside the repository (../shared)"
        done < <(grep -n '\.\./shared' "$file")
    fi
    dir=$(dirname "$file")
    # Inline links and images, then reference definitions; the target only
    # (an optional "title" after a space is dropped, <...> unwrapped).
    mapfile -t targets < <(
        {
            prose "$file" | grep -o '\](\(<[^>]*>\|[^) ]*\)[^)]*)' | sed -e 's/^](//' -e 's/)$//'
            prose "$file" | sed -n 's/^[[:space:]]\{0,3\}\[[^]]\{1,\}\]:[[:space:]]\{1,\}//p'
        } | sed -e 's/^<\([^>]*\)>.*/\1/' -e 's/[[:space:]].*//' | sort -u
    )
    for target in "${targets[@]}"; do
        [[ -z $target ]] && continue
        # URLs (http:, https:, mailto:, ...) are not checked.
        [[ $target =~ ^[A-Za-z][A-Za-z0-9+.-]*: ]] && continue
        path=${target%%#*}
        anchor=
        [[ $target == *"#"* ]] && anchor=${target#*#}
        if [[ -z $path ]]; then
            resolved=$file
        elif [[ $path == /* ]]; then
            resolved=${path#/}
        else
            resolved=$dir/$path
        fi
        if [[ ! -e $resolved ]]; then
            report "$file" "link to \`$target\`: $resolved does not exist"
            continue
        fi
        if [[ -n $anchor && -f $resolved && $resolved == *.md ]]; then
            if ! anchors "$resolved" | grep -xF -- "$anchor" >/dev/null; then
                report "$file" "link to \`$target\`: no heading of $resolved has the anchor #$anchor"
            fi
        fi
    done
done

if ((problems > 0)); then
    echo "check_links: $problems problem(s) in ${#files[@]} Markdown files" >&2
    exit 1
fi
echo "check_links: ${#files[@]} Markdown files, every relative link resolves"
