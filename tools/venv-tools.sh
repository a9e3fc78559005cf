# Sourced by the scripts that run a pinned Python tool (hadolint.sh,
# contract.sh, k8s-validate.sh): the tools live in .venv-tools/ at the
# repository root, made on first use.
#
#   source "$root/tools/venv-tools.sh"
#   venv_tools_install SCRIPT PACKAGE VERSION EXECUTABLE
#
# installs PACKAGE==VERSION into "$venv" (which the caller sets) unless
# that version is there already with its EXECUTABLE. A venv left by another Python (or a
# half-made one) is rebuilt.

venv_tools_install() {
    local script=$1 package=$2 version=$3 executable=$4 installed
    installed="$("$venv/bin/python" -c "import importlib.metadata as m; print(m.version('$package'))" 2>/dev/null || true)"
    if [[ -x "$executable" && "$installed" == "$version" ]]; then
        return 0
    fi
    echo "$script: installing $package==$version into $venv" >&2
    if [[ ! -x "$venv/bin/python" ]] || ! "$venv/bin/python" -c '' 2>/dev/null; then
        rm -rf "$venv"
        python3 -m venv "$venv"
    fi
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "$package==$version"
}
