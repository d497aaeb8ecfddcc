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
# audio, render); the code as a release /opt/fluorosim/releases/ID with its own virtualenv
# built from the hashed lock provisioning/requirements.lock, made current by one atomic
# rename of the symlink /opt/fluorosim/current (/opt/fluorosim/src and venv point through
# it); profiles in /etc/fluorosim with appliance.yaml naming the real devices;
# /var/lib/fluorosim; the systemd units and udev rules; the ledger's seal (a root-only key,
# its helper's socket); a persistent journal; boot straight into the service (enabled,
# multi-user target, no login prompt on any console, Ctrl-Alt-Del off, quiet boot, the GRUB
# menu locked with a password so nobody at the box can edit the kernel command line).
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
    pocl-opencl-icd                                   # the CPU's OpenCL where no GPU is, on any processor
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

install_nvidia_modules() {   # only where the tree has the driver: a module not there fails the boot's module loading
    local conf=/etc/modules-load.d/fluorosim-nvidia.conf found
    found=$(find "$ROOT/lib/modules" "$ROOT/usr/lib/modules" -name 'nvidia-uvm.ko*' 2>/dev/null || true)
    if [ -n "$found" ]; then
        install_file 0644 provisioning/modules-fluorosim-nvidia.conf "$conf"
    else
        rm -f "$ROOT$conf"
        echo "    no NVIDIA driver (nvidia-uvm.ko) under $ROOT/lib/modules: nothing to load"
    fi
}

code_tar() {   # the code as a reproducible tar stream: same tree, same bytes, same release id
    tar -C "$SRC" --exclude=__pycache__ --exclude='*.pyc' --exclude='*.egg-info' --sort=name --mtime=@0 \
        --owner=0 --group=0 --numeric-owner -cf - \
        appliance drivers configs systemd provisioning pyproject.toml README.md
}

RELEASE_ID=$(code_tar | sha256sum | cut -c1-12)
RELEASE=/opt/fluorosim/releases/$RELEASE_ID

install_code() {   # a new release beside the running one; nothing the service uses changes yet
    local dest="$ROOT$RELEASE/src" new="$ROOT$RELEASE/.src.new"
    if [ -d "$dest" ]; then
        echo "    release $RELEASE_ID is already there"
        return
    fi
    rm -rf "$new"
    install -d -m 0755 "$new"
    code_tar | tar -C "$new" --no-same-owner -xf -
    mv "$new" "$dest"
}

make_venv() {   # the release's own virtualenv, exactly the hashed lock, then its code on the path
    local venv=$RELEASE/venv
    if [ ! -x "$venv/bin/fluorosim" ]; then
        rm -rf "$venv"
        python3 -m venv "$venv"
        "$venv/bin/python" -m pip install -q --no-cache-dir --require-hashes --no-deps \
            -r "$RELEASE/src/provisioning/requirements.lock"
        "$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' \
            | { read -r site; echo "$RELEASE/src" > "$site/fluorosim.pth"; }
        printf '#!/bin/sh\nexec %s -m appliance "$@"\n' "$venv/bin/python" > "$venv/bin/fluorosim"
        chmod 0755 "$venv/bin/fluorosim"
    fi
}

activate_release() {   # one rename(2) makes the new code and its virtualenv current together
    local opt="$ROOT/opt/fluorosim"
    ln -sfn "releases/$RELEASE_ID" "$opt/.current.new"
    mv -T "$opt/.current.new" "$opt/current"
    [ -L "$opt/src" ] || { rm -rf "$opt/src"; ln -sfn current/src "$opt/src"; }
    [ -L "$opt/venv" ] || { rm -rf "$opt/venv"; ln -sfn current/venv "$opt/venv"; }
}

prune_releases() {   # keep the current release and the one before it, to go back to
    local opt="$ROOT/opt/fluorosim" keep r
    keep=$(printf '%s\n' "$RELEASE_ID"; ls -1t "$opt/releases" | { grep -vx "$RELEASE_ID" || true; } | head -n 1)
    for r in "$opt/releases"/*; do
        echo "$keep" | grep -qx "${r##*/}" || rm -rf "$r"
    done
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

make_identity() {   # the Device Observer UID (records/identity.py), never replaced: a new one is a new device
    local f="$ROOT/etc/fluorosim/device-identity"
    if [ ! -e "$f" ]; then
        python3 -c 'import uuid; print(f"2.25.{uuid.uuid4().int}")' > "$f.tmp"
        chmod 0644 "$f.tmp"
        mv "$f.tmp" "$f"
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

lock_consoles() {   # nobody at the box gets a login prompt, a reboot key or a kernel command line
    local n
    for n in 2 3 4 5 6; do
        link /dev/null "/etc/systemd/system/getty@tty$n.service"
        link /dev/null "/etc/systemd/system/autovt@tty$n.service"
    done
    link /dev/null /etc/systemd/system/ctrl-alt-del.target
    install_file 0644 provisioning/logind-fluorosim.conf /etc/systemd/logind.conf.d/fluorosim.conf
    install_file 0755 provisioning/grub-fluorosim-password /etc/grub.d/01_fluorosim_password
}

grub_password() {   # a random GRUB superuser password, its PBKDF2 hash root-only; kept once made
    local dir=/etc/fluorosim-seal pass
    install -d -m 0700 "$dir"
    if ! command -v grub-mkpasswd-pbkdf2 >/dev/null; then
        echo "    no grub-mkpasswd-pbkdf2 on this machine (package grub-common); lock the boot loader by hand"
        return
    fi
    if [ ! -s "$dir/grub.pbkdf2" ]; then
        pass=$(head -c 18 /dev/urandom | base64)
        printf '%s\n%s\n' "$pass" "$pass" | grub-mkpasswd-pbkdf2 | sed -n 's/.*is \(grub\.pbkdf2\..*\)$/\1/p' \
            > "$dir/grub.pbkdf2"
        chmod 0400 "$dir/grub.pbkdf2"
        printf '%s\n' "$pass" > "$dir/grub-password"
        chmod 0400 "$dir/grub-password"
        echo "    GRUB menu password written to $dir/grub-password (root only): note it, then delete that file"
    fi
    # The menu entries boot without the password; editing them or the GRUB shell needs it.
    grep -q -- '--unrestricted' /etc/grub.d/10_linux || \
        sed -i 's/^CLASS="--class gnu-linux --class gnu --class os/& --unrestricted/' /etc/grub.d/10_linux
}

seal_key() {
    /opt/fluorosim/venv/bin/fluorosim seal init --key /etc/fluorosim-seal/ledger.key
    install -d -m 0755 /var/lib/fluorosim-seal
}

apply_grub() {
    if command -v update-grub >/dev/null; then
        update-grub
    else
        echo "    no update-grub on this machine; set the kernel command line of /etc/default/grub.d/fluorosim.cfg by hand"
    fi
}

install_seal_units() {
    install_file 0644 systemd/fluorosim-seal.socket /etc/systemd/system/fluorosim-seal.socket
    install_file 0644 systemd/fluorosim-seal.service /etc/systemd/system/fluorosim-seal.service
    link /etc/systemd/system/fluorosim-seal.socket /etc/systemd/system/sockets.target.wants/fluorosim-seal.socket
}

start_service() {
    systemctl enable --now fluorosim-seal.socket
    systemctl restart fluorosim.service
}

# ---------------------------------------------------------------------------- run them

echo "fluorosim: installing from $SRC into ${ROOT:-/}"
system_step "install system packages: ${APT_PACKAGES[*]}" install_packages
file_step "install the service user's definition as /usr/lib/sysusers.d/fluorosim.conf" \
    install_file 0644 provisioning/sysusers-fluorosim.conf /usr/lib/sysusers.d/fluorosim.conf
system_step "create user fluorosim in groups video, input, dialout, audio, render (systemd-sysusers)" \
    systemd-sysusers /usr/lib/sysusers.d/fluorosim.conf
file_step "copy the code to the release $RELEASE (the running release is not touched)" install_code
system_step "create the release's virtualenv $RELEASE/venv from the hashed lock (pip --require-hashes)" make_venv
file_step "make release $RELEASE_ID current: atomic rename of /opt/fluorosim/current (src and venv point through it)" \
    activate_release
file_step "remove releases older than the current one and the one before it" prune_releases
file_step "install profiles into /etc/fluorosim (existing files are kept) with appliance.yaml for the real devices" \
    install_profiles
file_step "make the appliance's Device Observer UID once (/etc/fluorosim/device-identity)" make_identity
file_step "create /var/lib/fluorosim, /var/log/fluorosim and /var/cache/fluorosim" make_state_dirs
system_step "give the state folders to user fluorosim (chown)" own_state_dirs
file_step "install the unit /etc/systemd/system/fluorosim.service" \
    install_file 0644 systemd/fluorosim.service /etc/systemd/system/fluorosim.service
file_step "install the ledger seal helper's units fluorosim-seal.socket and fluorosim-seal.service" \
    install_seal_units
system_step "write the ledger key /etc/fluorosim-seal/ledger.key (root only, 0400; kept if there)" seal_key
file_step "install the udev rules /etc/udev/rules.d/99-fluorosim.rules (/dev/fluorosim/camera, keypad, pedal)" \
    install_file 0644 systemd/99-fluorosim.rules /etc/udev/rules.d/99-fluorosim.rules
file_step "load the device drivers at boot (/etc/modules-load.d/fluorosim.conf)" \
    install_file 0644 provisioning/modules-fluorosim.conf /etc/modules-load.d/fluorosim.conf
file_step "load NVIDIA's compute driver at boot where it is installed (/etc/modules-load.d/fluorosim-nvidia.conf)" \
    install_nvidia_modules
file_step "keep the journal across reboots (/var/log/journal, journald.conf.d/fluorosim.conf)" persistent_journal
system_step "apply the journal settings (systemd-tmpfiles, restart systemd-journald)" apply_journal
file_step "boot into the service: enable fluorosim.service, default multi-user.target, no getty on tty1, quiet boot" \
    boot_into_service
file_step "lock the consoles: no getty on tty2-6, no Ctrl-Alt-Del, logind spawns no consoles, GRUB menu password" \
    lock_consoles
system_step "set the GRUB menu password (random, hash root-only in /etc/fluorosim-seal) and boot entries unrestricted" \
    grub_password
system_step "reload systemd and udev (systemctl daemon-reload, udevadm control --reload, udevadm trigger)" apply_units
system_step "apply the boot settings (update-grub)" apply_grub
system_step "start the appliance (systemctl restart fluorosim.service)" start_service
echo "fluorosim: done"
