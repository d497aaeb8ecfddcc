#!/bin/bash
# Turn a fresh Debian 12 machine into the fluorosim appliance.
#
#   sudo provisioning/install.sh             install (or update) the appliance on this machine
#   provisioning/install.sh --dry-run        list every step, change nothing
#   provisioning/install.sh --root DIR       put the appliance's files into the tree DIR (an image
#                                            being built, or a test); steps that change the
#                                            running system (apt-get, systemd-sysusers, the
#                                            virtualenv, systemctl, update-grub) are listed as skipped
#
# What it does: system packages; the service user fluorosim (groups video, input, dialout,
# audio, render); the code in /opt/fluorosim/src and a virtualenv in /opt/fluorosim/venv;
# profiles in /etc/fluorosim with appliance.yaml naming the real devices; /var/lib/fluorosim;
# the systemd unit and udev rules; a persistent journal; boot straight into the service
# (enabled, multi-user target, no login prompt on tty1, quiet boot).
#
# Idempotent: a second run changes nothing, and an update keeps local edits to the profiles
# in /etc/fluorosim (files already there are left alone; units and rules are replaced).
set -euo pipefail
umask 022

SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
ROOT=""
DRY_RUN=0

APT_PACKAGES=(
    python3 python3-venv python3-dev gcc pkg-config  # the virtualenv; building systemd-python
    libsystemd-dev                                    # sd_notify and the journal from Python
    libhidapi-hidraw0 libusb-1.0-0                    # HID keypads
    ocl-icd-libopencl1                                # OpenCL loader for a GPU's ICD
    v4l-utils                                         # v4l2-ctl, to check the webcam
    alsa-utils                                        # the fluoroscopy time alarm
    fbset                                             # to check and set the framebuffer mode
)
PROFILE_KINDS=(fluoroscopes cases phantoms keymaps webcams exercises)

usage() {
    echo "usage: $0 [--dry-run] [--root DIR]" >&2
    exit 2
}

while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --root)
            [ $# -ge 2 ] && [ -n "$2" ] || { echo "install.sh: --root needs a directory" >&2; usage; }
            ROOT=$2
            shift ;;
        --root=*) ROOT=${1#--root=}; [ -n "$ROOT" ] || usage ;;
        -h|--help) sed -n '2,19p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "install.sh: unknown option $1" >&2; usage ;;
    esac
    shift
done

if [ -n "$ROOT" ]; then
    if [ "$DRY_RUN" = 0 ]; then
        mkdir -p "$ROOT"
    fi
    if [ -d "$ROOT" ]; then
        ROOT=$(cd "$ROOT" && pwd)
    fi
    [ "$ROOT" != "/" ] || ROOT=""
fi
if [ -z "$ROOT" ] && [ "$DRY_RUN" = 0 ] && [ "$(id -u)" != 0 ]; then
    echo "install.sh: run as root (sudo $0), or use --dry-run or --root DIR" >&2
    exit 2
fi

# A file step writes under $ROOT and runs in both modes; a system step changes the running
# machine and is skipped with --root. --dry-run only lists them.
file_step() {
    local what=$1
    shift
    if [ "$DRY_RUN" = 1 ]; then
        echo "would: $what"
        return
    fi
    echo "==> $what"
    "$@"
}

system_step() {
    local what=$1
    shift
    if [ -n "$ROOT" ]; then
        echo "skipped (--root): $what"
        return
    fi
    if [ "$DRY_RUN" = 1 ]; then
        echo "would: $what"
        return
    fi
    echo "==> $what"
    "$@"
}

# ---------------------------------------------------------------------------- the steps

install_packages() {
    apt-get update -q
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${APT_PACKAGES[@]}"
}

install_file() {   # install_file MODE SOURCE DEST (DEST under $ROOT); replaced every run
    install -D -m "$1" "$SRC/$2" "$ROOT$3"
}

install_code() {
    local dest="$ROOT/opt/fluorosim/src" new="$ROOT/opt/fluorosim/.src.new"
    rm -rf "$new"
    install -d -m 0755 "$new"
    tar -C "$SRC" --exclude=__pycache__ --exclude='*.pyc' --exclude='*.egg-info' --owner=0 --group=0 -cf - \
        appliance drivers configs systemd provisioning pyproject.toml README.md | tar -C "$new" --no-same-owner -xf -
    rm -rf "$dest"
    mv "$new" "$dest"
}

make_venv() {
    local venv=/opt/fluorosim/venv
    [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
    "$venv/bin/python" -m pip install -q --upgrade pip
    "$venv/bin/python" -m pip install -q --upgrade --no-cache-dir /opt/fluorosim/src
}

install_profiles() {
    local etc="$ROOT/etc/fluorosim" kind f
    install -d -m 0755 "$etc"
    for kind in "${PROFILE_KINDS[@]}"; do
        install -d -m 0755 "$etc/$kind"
        for f in "$SRC/configs/$kind"/*; do
            [ -f "$f" ] || continue
            if [ -e "$etc/$kind/${f##*/}" ]; then
                continue   # keep the site's version
            fi
            install -m 0644 "$f" "$etc/$kind/${f##*/}"
        done
    done
    if [ ! -e "$etc/appliance.yaml" ]; then
        install -m 0644 "$SRC/provisioning/appliance.yaml" "$etc/appliance.yaml"
    fi
}

make_state_dirs() {
    install -d -m 0750 "$ROOT/var/lib/fluorosim" "$ROOT/var/log/fluorosim" "$ROOT/var/cache/fluorosim"
}

own_state_dirs() {
    chown -R fluorosim:fluorosim /var/lib/fluorosim /var/log/fluorosim /var/cache/fluorosim
}

persistent_journal() {
    install -d -m 2755 "$ROOT/var/log/journal"
    install_file 0644 provisioning/journald-fluorosim.conf /etc/systemd/journald.conf.d/fluorosim.conf
}

apply_journal() {
    systemd-tmpfiles --create --prefix /var/log/journal
    systemctl restart systemd-journald.service
}

link() {   # link TARGET NAME (NAME under $ROOT): what systemctl enable, set-default and mask write
    install -d -m 0755 "$(dirname "$ROOT$2")"
    ln -sfn "$1" "$ROOT$2"
}

boot_into_service() {
    link /etc/systemd/system/fluorosim.service /etc/systemd/system/multi-user.target.wants/fluorosim.service
    link /lib/systemd/system/multi-user.target /etc/systemd/system/default.target
    # The appliance owns the screen: no login prompt on tty1, where the framebuffer is shown.
    link /dev/null /etc/systemd/system/getty@tty1.service
    link /dev/null /etc/systemd/system/autovt@tty1.service
    install_file 0644 provisioning/grub-fluorosim.cfg /etc/default/grub.d/fluorosim.cfg
}

apply_units() {
    systemctl daemon-reload
    udevadm control --reload
    udevadm trigger --action=add --subsystem-match=video4linux --subsystem-match=input \
        --subsystem-match=tty --subsystem-match=hidraw --subsystem-match=graphics
}

apply_grub() {
    if command -v update-grub >/dev/null; then
        update-grub
    else
        echo "    no update-grub on this machine; set the kernel command line of /etc/default/grub.d/fluorosim.cfg by hand"
    fi
}

start_service() {
    systemctl restart fluorosim.service
}

# ---------------------------------------------------------------------------- run them

echo "fluorosim: installing from $SRC into ${ROOT:-/}"
system_step "install system packages: ${APT_PACKAGES[*]}" install_packages
file_step "install the service user's definition as /usr/lib/sysusers.d/fluorosim.conf" \
    install_file 0644 provisioning/sysusers-fluorosim.conf /usr/lib/sysusers.d/fluorosim.conf
system_step "create user fluorosim in groups video, input, dialout, audio, render (systemd-sysusers)" \
    systemd-sysusers /usr/lib/sysusers.d/fluorosim.conf
file_step "copy the code to /opt/fluorosim/src" install_code
system_step "create the virtualenv /opt/fluorosim/venv and install fluorosim into it (pip)" make_venv
file_step "install profiles into /etc/fluorosim (existing files are kept) with appliance.yaml for the real devices" \
    install_profiles
file_step "create /var/lib/fluorosim, /var/log/fluorosim and /var/cache/fluorosim" make_state_dirs
system_step "give the state folders to user fluorosim (chown)" own_state_dirs
file_step "install the unit /etc/systemd/system/fluorosim.service" \
    install_file 0644 systemd/fluorosim.service /etc/systemd/system/fluorosim.service
file_step "install the udev rules /etc/udev/rules.d/99-fluorosim.rules (/dev/fluorosim/camera, keypad, pedal)" \
    install_file 0644 systemd/99-fluorosim.rules /etc/udev/rules.d/99-fluorosim.rules
file_step "load the device drivers at boot (/etc/modules-load.d/fluorosim.conf)" \
    install_file 0644 provisioning/modules-fluorosim.conf /etc/modules-load.d/fluorosim.conf
file_step "keep the journal across reboots (/var/log/journal, journald.conf.d/fluorosim.conf)" persistent_journal
system_step "apply the journal settings (systemd-tmpfiles, restart systemd-journald)" apply_journal
file_step "boot into the service: enable fluorosim.service, default multi-user.target, no getty on tty1, quiet boot" \
    boot_into_service
system_step "reload systemd and udev (systemctl daemon-reload, udevadm control --reload, udevadm trigger)" apply_units
system_step "apply the boot settings (update-grub)" apply_grub
system_step "start the appliance (systemctl restart fluorosim.service)" start_service
echo "fluorosim: done"
