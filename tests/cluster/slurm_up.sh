#!/usr/bin/env bash
# Brings up a single-node SLURM on this machine for the cluster test (make test-cluster): Debian's
# slurmctld, slurmd and munge, with slurmdbd on MariaDB so that sacct reports finished jobs (the
# executor plugin's status command). Needs root; installs the packages when they are missing.
# Idempotent: daemons already answering are left as they are. Exit status 77: SLURM cannot be set
# up here (the one line on stderr says why); any other failure is a broken harness.
set -euo pipefail

PACKAGES="slurmctld slurmd slurm-client slurmdbd munge mariadb-server"
CLUSTER=dmais
PARTITION=${DMAIS_TEST_PARTITION:-debug}
ACCOUNT=${DMAIS_TEST_ACCOUNT:-dmais}
ETC=/etc/slurm
SPOOL=/var/spool/slurm
LOG=/var/log/slurm

skip() { echo "SLURM cannot be set up here: $*" >&2; exit 77; }

wait_for() {  # wait_for SECONDS WHAT COMMAND...: until COMMAND succeeds
    local seconds=$1 what=$2; shift 2
    for _ in $(seq "$((seconds * 4))"); do
        "$@" >/dev/null 2>&1 && return 0
        sleep 0.25
    done
    echo "slurm_up: $what did not come up within ${seconds} s" >&2
    return 1
}

install_packages() {
    local missing=()
    for command in slurmctld slurmd sbatch slurmdbd munged mariadbd; do
        command -v "$command" >/dev/null 2>&1 || missing+=("$command")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" -eq 0 ] || skip "not root, and ${missing[*]} not installed"
    command -v apt-get >/dev/null 2>&1 || skip "no apt-get to install ${missing[*]}"
    echo "slurm_up: installing $PACKAGES" >&2
    # policy-rc.d keeps the packages' init scripts from starting daemons with their own configs
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q $PACKAGES >/dev/null \
        || { apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $PACKAGES >/dev/null; } \
        || skip "apt-get could not install $PACKAGES"
}

start_munge() {
    munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && return 0
    [ -s /etc/munge/munge.key ] || { mungekey --create --force 2>/dev/null || dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 2>/dev/null; }
    chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    runuser -u munge -- /usr/sbin/munged
    wait_for 20 munge sh -c 'munge -n | unmunge'
}

start_mariadb() {
    mariadb -e 'select 1' >/dev/null 2>&1 || {
        [ -d /var/lib/mysql/mysql ] || mariadb-install-db --user=mysql --datadir=/var/lib/mysql >/dev/null
        mkdir -p /run/mysqld && chown mysql:mysql /run/mysqld
        (mysqld_safe --user=mysql >/dev/null 2>&1 &)
        wait_for 60 MariaDB mariadb -e 'select 1'
    }
    mariadb -e "CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'slurm';
                GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;"
}

write_configs() {
    local host node
    host=$(hostname -s)
    # the node as slurmd sees it, with memory left for the daemons
    node=$(slurmd -C | head -1)
    local memory=${node##*RealMemory=}
    node="${node%%RealMemory=*}RealMemory=$((memory * 9 / 10))"
    mkdir -p "$ETC" "$SPOOL/ctld" "$SPOOL/d" "$LOG"
    cat > "$ETC/slurm.conf" <<CONF
ClusterName=$CLUSTER
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$SPOOL/ctld
SlurmdSpoolDir=$SPOOL/d
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOG/slurmctld.log
SlurmdLogFile=$LOG/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
ReturnToService=2
MpiDefault=none
SchedulerType=sched/backfill
AccountingStoreFlags=job_comment
$node State=UNKNOWN
PartitionName=$PARTITION Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
    cat > "$ETC/slurmdbd.conf" <<CONF
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
PidFile=/run/slurmdbd.pid
LogFile=$LOG/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=slurm
StorageLoc=slurm_acct_db
CONF
    chmod 600 "$ETC/slurmdbd.conf"
}

start_slurm() {
    sacctmgr -n list cluster >/dev/null 2>&1 || { slurmdbd; wait_for 60 slurmdbd sacctmgr -n list cluster; }
    sacctmgr -n list cluster format=cluster | grep -qw "$CLUSTER" || sacctmgr -i add cluster "$CLUSTER" >/dev/null
    sacctmgr -n list account format=account | grep -qw "$ACCOUNT" || sacctmgr -i add account "$ACCOUNT" cluster="$CLUSTER" >/dev/null
    sacctmgr -n list assoc user=root account="$ACCOUNT" format=user | grep -qw root \
        || sacctmgr -i add user root account="$ACCOUNT" cluster="$CLUSTER" >/dev/null
    scontrol ping 2>/dev/null | grep -q UP || { slurmctld; wait_for 60 slurmctld sh -c 'scontrol ping | grep -q UP'; }
    pgrep -x slurmd >/dev/null || slurmd
    wait_for 60 "node $(hostname -s)" sh -c "sinfo -h -N -o %t | grep -Eq '^(idle|mix|alloc)'"
}

install_packages
start_munge
start_mariadb
[ -f "$ETC/slurm.conf" ] && scontrol ping 2>/dev/null | grep -q UP || write_configs
start_slurm
echo "slurm_up: cluster $CLUSTER, partition $PARTITION (default), account $ACCOUNT: $(sinfo -h -o '%D node(s), %c CPUs, %m MB')" >&2
