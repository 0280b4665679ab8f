#!/usr/bin/env bash
# What the test suite needs besides Python packages: Debian's chromium (the session page's browser tests drive it
# through Playwright), iproute2's `ip` (the across-hosts tests make network namespaces) and tcpdump (the fleet test
# captures the stack's traffic to check nothing crosses in clear text). Installed with apt-get
# where they are missing and apt-get can run; otherwise one line says what to install, and the exit status is 1.
set -euo pipefail
missing=()
[ -x /usr/bin/chromium ] || missing+=(chromium)
command -v ip >/dev/null 2>&1 || missing+=(iproute2)
command -v tcpdump >/dev/null 2>&1 || [ -x /usr/bin/tcpdump ] || missing+=(tcpdump)
[ ${#missing[@]} -eq 0 ] && exit 0
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
  echo "installing ${missing[*]} (Debian packages the tests need)"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  exit 0
fi
if command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  echo "installing ${missing[*]} (Debian packages the tests need)"
  sudo -n apt-get update -qq && sudo -n env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  exit 0
fi
echo "make test needs: ${missing[*]} (Debian: apt-get install ${missing[*]}); install them and run make test again" >&2
exit 1
