#!/usr/bin/env bash
# Brings up a SLURM of several nodes on this machine for the cluster test (make test-cluster): Debian's
# slurmctld, slurmdbd on MariaDB (so that sacct reports finished jobs, the executor plugin's status
# command) and munge on this host, and NODES slurmd nodes (DMAIS_TEST_NODES, default 3: n1, n2, ...),
# each in its own network namespace (dmais-n1, ...) and host name, on a bridge (dmais-br, 10.77.0.0/24:
# the controller 10.77.0.1, node k 10.77.0.(10+k)) and no route elsewhere. The nodes share this file
# system, as a cluster's nodes share its storage. Needs root; installs the packages when they are missing.
#
#   slurm_up.sh            up: idempotent; daemons already answering are left as they are, a node whose
#                          slurmd is gone is started again (how the test brings a killed node back)
#   slurm_up.sh kill NODE  NODE dies as in a power loss: every process in its namespace (its slurmd and
#                          every process of its jobs) killed with SIGKILL; the controller marks it down
#                          after SlurmdTimeout
#   slurm_up.sh down       the nodes, slurmctld and slurmdbd stopped, the namespaces and the bridge removed
#                          (munge and MariaDB are left running)
#
# Exit status 77: SLURM cannot be set up here (the one line on stderr says why); any other failure is a
# broken harness.
set -euo pipefail

PACKAGES="slurmctld slurmd slurm-client slurmdbd munge mariadb-server"
CLUSTER=dmais
PARTITION=${DMAIS_TEST_PARTITION:-debug}
ACCOUNT=${DMAIS_TEST_ACCOUNT:-dmais}
ETC=/etc/slurm
SPOOL=/var/spool/slurm
LOG=/var/log/slurm
NODES=${DMAIS_TEST_NODES:-3}
BRIDGE=dmais-br
NET=10.77.0
CONTROLLER=$NET.1

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

node_names() { seq -f 'n%g' 1 "$NODES"; }
namespace() { echo "dmais-$1"; }            # a node's network namespace
address() { echo "$NET.$((10 + ${1#n}))"; }  # a node's address on the bridge

slurm_conf() {  # the cluster's slurm.conf, on stdout
    local host node memory
    host=$(hostname -s)
    # a node as slurmd sees this machine (every node has its CPUs), with a share of the memory that
    # leaves room for the daemons
    node=$(slurmd -C | head -1)
    memory=${node##*RealMemory=}
    node=${node#NodeName=* }
    node="${node%%RealMemory=*}RealMemory=$((memory * 9 / 10 / NODES))"
    cat <<CONF
ClusterName=$CLUSTER
SlurmctldHost=$host($CONTROLLER)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$SPOOL/ctld
SlurmdSpoolDir=$SPOOL/d-%n
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd-%n.pid
SlurmctldLogFile=$LOG/slurmctld.log
SlurmdLogFile=$LOG/slurmd-%n.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=$CONTROLLER
AccountingStoreFlags=job_comment
MpiDefault=none
SchedulerType=sched/backfill
# a node that stops answering is down after 20 s, its jobs NODE_FAIL; it serves again once its slurmd
# registers
SlurmdTimeout=20
ReturnToService=2
CONF
    for name in $(node_names); do
        echo "NodeName=$name NodeAddr=$(address "$name") NodeHostname=$name $node State=UNKNOWN"
    done
    echo "PartitionName=$PARTITION Nodes=ALL Default=YES MaxTime=INFINITE State=UP"
}

write_dbd_conf() {
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

alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }  # alive PIDFILE

start_network() {  # the bridge and each node's namespace with its end of a veth pair
    command -v ip >/dev/null && command -v nsenter >/dev/null || skip "no ip or nsenter (iproute2, util-linux)"
    ip link show "$BRIDGE" >/dev/null 2>&1 || {
        ip link add "$BRIDGE" type bridge || skip "cannot make a network bridge here"
        ip addr add "$CONTROLLER/24" dev "$BRIDGE"
    }
    ip link set "$BRIDGE" up
    local name netns
    for name in $(node_names); do
        netns=$(namespace "$name")
        [ -e "/var/run/netns/$netns" ] || ip netns add "$netns"
        ip link show "dmais-v${name#n}" >/dev/null 2>&1 \
            || ip link add "dmais-v${name#n}" type veth peer name eth0 netns "$netns"
        ip link set "dmais-v${name#n}" master "$BRIDGE" up
        nsenter --net="/var/run/netns/$netns" sh -ec "
            ip addr show dev eth0 | grep -q ' $(address "$name")/' || ip addr add $(address "$name")/24 dev eth0
            ip link set eth0 up; ip link set lo up"
    done
}

start_node() {  # start_node NAME: its slurmd in its namespace, with its own host name
    # nsenter, not `ip netns exec`, which remounts /sys and hides the cgroup mounts slurmd needs
    nsenter --net="/var/run/netns/$(namespace "$1")" unshare --uts sh -c "hostname $1 && exec slurmd -N $1"
}

start_slurm() {
    sacctmgr -n list cluster >/dev/null 2>&1 || { slurmdbd; wait_for 60 slurmdbd sacctmgr -n list cluster; }
    sacctmgr -n list cluster format=cluster | grep -qw "$CLUSTER" || sacctmgr -i add cluster "$CLUSTER" >/dev/null
    sacctmgr -n list account format=account | grep -qw "$ACCOUNT" || sacctmgr -i add account "$ACCOUNT" cluster="$CLUSTER" >/dev/null
    sacctmgr -n list assoc user=root account="$ACCOUNT" format=user | grep -qw root \
        || sacctmgr -i add user root account="$ACCOUNT" cluster="$CLUSTER" >/dev/null
    scontrol ping 2>/dev/null | grep -q UP || { slurmctld; wait_for 60 slurmctld sh -c 'scontrol ping | grep -q UP'; }
    local name
    for name in $(node_names); do
        alive "/run/slurmd-$name.pid" || start_node "$name"
    done
    wait_for 90 "$NODES node(s)" sh -c "[ \$(sinfo -h -N -o %t | grep -Ec '^(idle|mix|alloc)') -eq $NODES ]"
}

stop_daemons() {  # every slurmd, slurmctld and slurmdbd this script starts (and a single-node setup's)
    local pidfile
    for pidfile in /run/slurmd-*.pid /run/slurmd.pid /run/slurmctld.pid /run/slurmdbd.pid; do
        alive "$pidfile" && kill "$(cat "$pidfile")"
        for _ in $(seq 40); do alive "$pidfile" || break; sleep 0.25; done
        rm -f "$pidfile"
    done
}

up() {
    install_packages
    start_munge
    start_mariadb
    mkdir -p "$ETC" "$SPOOL/ctld" "$LOG"
    [ -f "$ETC/slurmdbd.conf" ] || write_dbd_conf
    local conf
    conf=$(slurm_conf)
    if [ "$(cat "$ETC/slurm.conf" 2>/dev/null)" != "$conf" ]; then  # another cluster: start over with this one
        stop_daemons
        echo "$conf" > "$ETC/slurm.conf"
    fi
    start_network
    start_slurm
    echo "slurm_up: cluster $CLUSTER, partition $PARTITION (default), account $ACCOUNT: $(sinfo -h -o '%D node(s) %N, %c CPUs, %m MB each')" >&2
}

kill_node() {  # kill_node NAME
    local netns pids
    netns=$(namespace "$1")
    [ -e "/var/run/netns/$netns" ] || { echo "slurm_up: no node $1" >&2; exit 2; }
    pids=$(ip netns pids "$netns")
    [ -z "$pids" ] || kill -KILL $pids
    rm -f "/run/slurmd-$1.pid"
    echo "slurm_up: node $1 killed ($(echo $pids | wc -w) processes)" >&2
}

down() {
    stop_daemons
    local netns
    for netns in $(ip netns list | grep -o '^dmais-n[0-9]*'); do
        pids=$(ip netns pids "$netns")
        [ -z "$pids" ] || kill -KILL $pids
        ip netns delete "$netns"
    done
    ! ip link show "$BRIDGE" >/dev/null 2>&1 || ip link delete "$BRIDGE"
    echo "slurm_up: SLURM stopped, its namespaces and bridge removed" >&2
}

case "${1:-up}" in
    up) up ;;
    kill) [ $# -eq 2 ] || { echo "usage: slurm_up.sh kill NODE" >&2; exit 2; }; kill_node "$2" ;;
    down) down ;;
    *) echo "usage: slurm_up.sh [up | kill NODE | down]" >&2; exit 2 ;;
esac
