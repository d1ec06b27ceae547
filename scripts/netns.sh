#!/usr/bin/env bash
# Several hosts on one machine (issue 42): Linux network namespaces joined by veth pairs to a
# bridge that lives in a namespace of its own, so nothing touches the host's interfaces,
# routes or addresses.
#
#   scripts/netns.sh up PREFIX N        build PREFIX-br (the bridge br0), PREFIX-learner,
#                                       PREFIX-prom and PREFIX-a1 .. PREFIX-aN; print one JSON
#                                       line per host: {"host","netns","addr","dev"}
#   scripts/netns.sh down PREFIX        kill what still runs in them and delete them (idempotent)
#   scripts/netns.sh cut PREFIX HOST    take HOST's link down (the bridge side of its veth)
#   scripts/netns.sh uncut PREFIX HOST  bring it up again
#   scripts/netns.sh trickle PREFIX HOST    tbf 64 kbit/s both ways on HOST's link
#   scripts/netns.sh untrickle PREFIX HOST  remove it
#   scripts/netns.sh hosts PREFIX N     print the JSON lines of `up` without building anything
#
# HOST is learner, prom or aI. Every host has eth0 with 10.S.0.X/24 (S = $NETNS_SUBNET, 200 by
# default; learner .1, prom .2, actor i .(10+i)); its peer in PREFIX-br is called ve-HOST.
# The addresses exist only inside the namespaces, so two networks with different prefixes do
# not collide. Needs root and iproute2 with `ip netns`; elsewhere it exits 77 (skip) saying why.
set -euo pipefail

SUBNET=${NETNS_SUBNET:-200}
TBF=(tbf rate 64kbit burst 16kb latency 400ms)

skip() {
    echo "netns.sh: skipped: $*" >&2
    exit 77
}
die() {
    echo "netns.sh: $*" >&2
    exit 2
}

usage() {
    sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
}

preflight() {
    [[ $(id -u) -eq 0 ]] || skip "needs root (network namespaces, veth pairs and a bridge)"
    command -v ip >/dev/null || skip "iproute2's ip is not installed"
    ip netns list >/dev/null 2>&1 || skip "ip netns is unavailable here"
}

# host name -> "netns addr dev"
host_info() {
    local prefix=$1 host=$2
    case $host in
        learner) echo "$prefix-learner 10.$SUBNET.0.1 ve-learner" ;;
        prom) echo "$prefix-prom 10.$SUBNET.0.2 ve-prom" ;;
        a[0-9]*)
            local i=${host#a}
            ((i >= 1 && i <= 200)) || die "actor index $i out of 1..200"
            echo "$prefix-$host 10.$SUBNET.0.$((10 + i)) ve-$host"
            ;;
        *) die "unknown host $host (learner, prom or aI)" ;;
    esac
}

hosts() {
    local n=$2
    echo learner prom
    for ((i = 1; i <= n; i++)); do echo "a$i"; done
}

print_hosts() {
    local prefix=$1 n=$2 host ns addr dev
    for host in $(hosts "$prefix" "$n"); do
        read -r ns addr dev < <(host_info "$prefix" "$host")
        printf '{"host":"%s","netns":"%s","addr":"%s","dev":"%s","bridge_netns":"%s-br"}\n' \
            "$host" "$ns" "$addr" "$dev" "$prefix"
    done
}

down() {
    local prefix=$1 ns pid
    # Ours: PREFIX-br, PREFIX-learner, PREFIX-prom, PREFIX-aI. Deleting a namespace deletes the
    # veth ends in it, and with them their peers.
    for ns in $(ip netns list 2>/dev/null | awk '{print $1}' |
        grep -E "^${prefix}-(br|learner|prom|a[0-9]+)$" || true); do
        # A process still inside would keep the namespace alive after its name is gone.
        for pid in $(ip netns pids "$ns" 2>/dev/null || true); do
            kill -KILL "$pid" 2>/dev/null || true
        done
        ip netns del "$ns" 2>/dev/null || true
    done
}

up() {
    local prefix=$1 n=$2 host ns addr dev br=$1-br
    [[ $n =~ ^[0-9]+$ ]] && ((n >= 1 && n <= 200)) || die "N must be 1..200, not $n"
    [[ $prefix =~ ^[A-Za-z0-9_.-]{1,40}$ ]] || die "PREFIX must be 1-40 of [A-Za-z0-9_.-]"
    down "$prefix"
    trap 'down "$prefix"' ERR
    ip netns add "$br" || skip "cannot create a network namespace (ip netns add failed)"
    ip -n "$br" link set lo up
    ip -n "$br" link add br0 type bridge || skip "cannot create a bridge in a namespace"
    ip -n "$br" link set br0 up
    for host in $(hosts "$prefix" "$n"); do
        read -r ns addr dev < <(host_info "$prefix" "$host")
        ip netns add "$ns"
        ip -n "$ns" link set lo up
        ip -n "$br" link add "$dev" type veth peer name eth0 netns "$ns"
        ip -n "$br" link set "$dev" master br0 up
        ip -n "$ns" addr add "$addr/24" dev eth0
        ip -n "$ns" link set eth0 up
    done
    trap - ERR
    print_hosts "$prefix" "$n"
}

link() {
    local action=$1 prefix=$2 host=$3 ns addr dev br=$2-br
    read -r ns addr dev < <(host_info "$prefix" "$host")
    case $action in
        cut) ip -n "$br" link set "$dev" down ;;
        uncut) ip -n "$br" link set "$dev" up ;;
        # Both directions: the bridge side shapes what reaches the host, eth0 what it sends.
        trickle)
            tc -n "$br" qdisc replace dev "$dev" root "${TBF[@]}"
            tc -n "$ns" qdisc replace dev eth0 root "${TBF[@]}"
            ;;
        untrickle)
            tc -n "$br" qdisc del dev "$dev" root 2>/dev/null || true
            tc -n "$ns" qdisc del dev eth0 root 2>/dev/null || true
            ;;
    esac
}

[[ $# -ge 2 ]] || usage
cmd=$1
shift
case $cmd in
    up)
        [[ $# -eq 2 ]] || usage
        preflight
        up "$1" "$2"
        ;;
    down)
        [[ $# -eq 1 || $# -eq 2 ]] || usage
        preflight
        down "$1"
        ;;
    cut | uncut | trickle | untrickle)
        [[ $# -eq 2 ]] || usage
        preflight
        link "$cmd" "$1" "$2"
        ;;
    hosts)
        [[ $# -eq 2 ]] || usage
        print_hosts "$1" "$2"
        ;;
    *) usage ;;
esac
