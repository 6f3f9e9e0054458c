"""The round core both drivers share (agents/rounds.py, agents/omniscient.py): the
omniscient adversary's view read off the simulator's nodes equals the one read off the
network's messages; payload unpacking; link counters; the rows an agent reads; the
dashboard's frames; and what importing the core costs an agent process."""

import subprocess
import sys

import numpy as np

from agents.api import load_experiment
from agents.middleware import make_channel, make_nodes
from agents.net.view import NetworkView
from agents.omniscient import NodesView, OmniscientView, reads_view, view_topology
from agents.plant import PlantRole
from agents.rounds import DashboardFeed, Reads, addressed, count_fate, link_rows, links_of, links_table, receiver_counters, round_order, round_rank
from agents.simulate import deliver, simulate
from estimation.base import MaskedInputs
from tests.conftest import SCENARIOS
from transport.byzantine import Forged
from transport.channel import LinkCounters


def test_round_order_puts_the_byzantine_agents_last_by_index():
    assert round_order(6, {4, 1}) == [0, 2, 3, 5, 1, 4]
    assert round_rank((10, 20, 30, 40), {0}) == {20: 0, 30: 1, 40: 2, 10: 3}
    assert round_order(3, ()) == [0, 1, 2]


def test_addressed_unpacks_arrays_forged_stamps_and_omissions():
    a, b, c = np.array([1.0]), np.array([2.0]), np.array([3.0])
    msg = {7: a, 3: Forged(11, b), 5: None, 9: c}  # 4: missing
    got = addressed(msg, 6, [3, 4, 5, 7, 9])
    assert [(j, s) for j, s, _ in got] == [(3, 11), (7, 6), (9, 6)]  # the receivers' order
    assert got[0][2] is b and got[1][2] is a and got[2][2] is c
    assert isinstance(got[0][1], int)


def test_deliver_hands_each_receiver_its_own_payload_and_stamp():
    exp, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ("run.duration=0.5", "expect=[]"), None)
    nodes = make_nodes(exp, make_channel(exp))
    src = nodes[0]
    targets = [nodes[j] for j in exp.out_neighbours(0)]
    assert len(targets) >= 2
    first, second = targets[0], targets[1]
    msg = {first.id: Forged(4, np.full(exp.n, 9.0)), second.id: None}
    deliver(src, 2, msg, targets)
    # the forged stamp decides when the receiver's (perfect) channel shows it: round 5
    assert first.open_round(4) == {} and first.links[src.id].sent == 1
    assert first.open_round(5)[0].stamp == 4 and np.all(first.inbox[0].value == 9.0)
    assert second.links[src.id].sent == 0 and second.open_round(5) == {}


def test_count_fate_counts_as_the_receivers_node():
    c = LinkCounters()
    count_fate(c, None, 3)
    count_fate(c, 4, 3)
    count_fate(c, 6, 3)
    assert (c.delivered, c.dropped, c.late) == (2, 1, 1)


def test_link_rows_and_the_table_of_the_simulator():
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=30", "expect=[]"), None)
    res = simulate(exp)
    assert any(v["dropped"] for v in res.links.values())
    nodes = make_nodes(exp, make_channel(exp))
    for nd in nodes:  # counters as a run leaves them
        for j, c in nd.links.items():
            c.sent, c.delivered, c.dropped, c.late, c.rejected = j, 2 * j, 3, 4, nd.id
    rows = link_rows(nodes[2].links)
    assert rows.shape == (len(exp.in_neighbours(2)), 6)
    assert [int(r[0]) for r in rows] == list(nodes[2].links)  # in-neighbour order
    table = links_table((nd.id, link_rows(nd.links)) for nd in nodes)
    assert table == links_of(nodes)
    j = next(iter(nodes[2].links))
    assert table[f"{j}->{nodes[2].id}"] == {"sent": j, "delivered": 2 * j, "dropped": 3, "late": 4,
                                             "rejected": nodes[2].id}
    counters = receiver_counters(nodes)
    deg = len(nodes[2].links)
    assert counters[2].tolist() == [2 * sum(nodes[2].links), 3 * deg, 4 * deg, nodes[2].id * deg]


def test_reads_follow_the_patrols():
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=30",), None)
    reads = Reads(exp)
    assert not reads.static
    y = np.arange(float(sum(len(r) for r in exp.bank_rows)))
    commuting = 0
    for k in range(30):
        for i in range(exp.N):
            rows = exp.rows_at(i, k)
            got = reads.measurement(i, k, y)
            if rows is None:
                commuting += 1
                assert got is None and reads.rows(i, k) is None
            else:
                assert np.array_equal(got, y[rows])
    assert commuting > 0
    static, _ = load_experiment(SCENARIOS / "lee_kim_shim.toml", ("run.duration=0.5", "expect=[]"), None)
    r = Reads(static)
    assert r.static and np.array_equal(r.rows(1, 3), static.agent_rows[1])


def test_the_view_off_the_nodes_equals_the_view_off_the_messages():
    """mitra_cells.toml (drops with p = 0.32, mobile agents, LFRE receivers masking inputs
    by mode, agent 5 cancelling): in every round, before the adversary acts, the values it
    would read for each receiver are the same arrays whether read off the receivers' nodes
    (the simulator) or off the messages of the round and the channel model (the network)."""
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=60", "expect=[]"), None)
    channel = make_channel(exp)
    nodes = make_nodes(exp, channel)
    (b,) = exp.byzantine
    me = nodes[b]
    assert reads_view(me.strategy)
    topo = view_topology(exp, me.id, {nd.id: nd.estimator for nd in nodes})
    assert topo.masks and any(not np.all(m == 1) for ms in topo.masks.values() for m in ms.values())
    assert all(isinstance(nodes[exp.agent_ids.index(j)].estimator, MaskedInputs) for j in topo.masks)
    sim_view, net_view = NodesView(topo, nodes), NetworkView(topo, make_channel(exp))
    assert isinstance(sim_view, OmniscientView) and isinstance(net_view, OmniscientView)
    me.view = sim_view
    plant, reads = PlantRole(exp), Reads(exp)
    targets = [[nodes[j] for j in exp.out_neighbours(i)] for i in range(exp.N)]
    compared = fewer = 0
    for k in range(exp.n_rounds + 1):
        y = plant.measure(k)
        sim_view.k = k
        net_view.forget(k)
        for i in round_order(exp.N, exp.byzantine):
            node = nodes[i]
            if i == b:  # the adversary's turn: compare what both views show it
                for j in topo.out:
                    a, c = sim_view.others_for(j, me.id), net_view.others_for(j, me.id)
                    assert len(a) == len(c)
                    assert all(np.array_equal(u, v) for u, v in zip(a, c))
                    compared += bool(a)
                    fewer += len(a) < len(topo.before[j])
            out = node.run_round(k, reads.measurement(i, k, y))
            msg = node.publish(k, out) if node.strategy is not None else out
            deliver(node, k, msg, targets[i])
            if isinstance(msg, dict):
                for j, stamp, value in addressed(msg, k, node.out_neighbours):
                    if net_view.wants(node.id, j):
                        net_view.add(node.id, j, stamp, value)
            elif net_view.wants(node.id, None):
                net_view.add(node.id, None, k, msg)
        if k < exp.n_rounds:
            plant.advance(k)
    assert compared > 30  # the view had values to show in most rounds
    assert fewer > 0  # and the channel dropped some of them


def test_the_view_needs_the_simulators_order_not_the_arrival_order():
    """A view reads senders in the round's order, whatever order their messages came in."""
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=5", "expect=[]"), None)
    (b,) = exp.byzantine
    topo = view_topology(exp, exp.agent_ids[b], {})
    rank = round_rank(exp.agent_ids, exp.byzantine)
    for before in topo.before.values():
        assert list(before) == sorted(before, key=rank.__getitem__)
        assert exp.agent_ids[b] not in before
    assert topo.masks == {}  # no estimators given: every component counts


class _Dash:
    def __init__(self):
        self.logged = []

    def is_map_frame(self, k):
        return k % 2 == 0

    def log_chunk(self, rows, mon, *, x, est, delivered, counters):
        self.logged.append((list(rows), delivered, counters))


def test_dashboard_feed_hands_frames_of_map_rounds_and_counters():
    dash = _Dash()
    feed = DashboardFeed(dash, 3, lambda: np.ones((3, 4)))
    assert feed.wants(2) and not feed.wants(3)
    feed.set_arrivals(2, [[1], [], [0, 1]])
    feed.frame(6)[1, 2] = True
    feed.log(np.array([1, 2, 3, 4]), None, None, None)
    rows, delivered, counters = dash.logged[0]
    assert set(delivered) == {2, 4}  # map rounds only; round 4 had no frame: no links
    assert delivered[2].tolist() == [[False, True, False], [False, False, False], [True, True, False]]
    assert not delivered[4].any() and counters.shape == (3, 4)
    assert list(feed.frames) == [6]  # a later chunk's frame is kept


def test_the_round_core_is_lean():
    """An agent process imports the core: not the scenario schema, pyarrow, Rerun, cvxpy,
    networkx or click."""
    modules = ("agents.rounds", "agents.omniscient", "agents.node", "agents.net.view")
    code = (f"import sys\nimport {', '.join(modules)}\n"
            "print(sorted(m for m in ('scenarios.schema', 'scenarios.build', 'pydantic', 'pyarrow', 'rerun', "
            "'cvxpy', 'networkx', 'click') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_an_adversarys_slice_unpickles_without_the_heavy_stack(tmp_path):
    """The omniscient adversary's slice (its node and its view's topology, agents.omniscient)
    is read by an agent process without the scenario schema, pyarrow, Rerun, cvxpy,
    networkx or click."""
    from agents.net.slices import agent_slices, dumps_slice

    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=5", "expect=[]"), None)
    (b,) = exp.byzantine
    part = agent_slices(exp)[b]
    assert part.view is not None and part.view.masks
    path = tmp_path / "agent.pkl"
    path.write_bytes(dumps_slice(part))
    code = ("import sys\nfrom agents.net.slices import read_slice\n"
            f"p = read_slice(__import__('pathlib').Path({str(path)!r}))\n"
            "assert type(p.view).__module__ == 'agents.omniscient', type(p.view)\n"
            "print(sorted(m for m in ('scenarios.schema', 'scenarios.build', 'pydantic', 'pyarrow', 'rerun', "
            "'cvxpy', 'networkx', 'click') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_the_fork_servers_preload_covers_the_channels_first_draws():
    """What the fork server preloads (agents.net.startup.PRELOAD) covers the channel model's
    draws (Channel.prepare before round 0, fate() after): a forked agent imports nothing
    for them (numpy.random took 15-40 ms of CPU in each agent process)."""
    code = ("import sys, importlib\nfrom agents.net.startup import PRELOAD\n"
            "for m in PRELOAD: importlib.import_module(m)\n"
            "before = set(sys.modules)\nfrom transport.channel import Channel\n"
            "ch = Channel(seed=1, drop_p=0.2, delay_max=1)\nch.prepare([(1, 2)])\nch.fate(2, 1, 3000)\n"
            "print(sorted(set(sys.modules) - before))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_views_missing_count_is_what_its_agent_sleeps_for():
    """NetworkView.missing(k): the live agents the view needs that have not reported round
    k, plus one while a reported message has not arrived; 0 exactly when ready(k). The
    lockstep adversary sleeps until that many messages came (a lower bound: never more)."""
    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=5", "expect=[]"), None)
    (b,) = exp.byzantine
    topo = view_topology(exp, exp.agent_ids[b], {})
    view = NetworkView(topo, make_channel(exp))
    view.forget(3)
    needed = list(topo.needed)
    assert len(needed) >= 3
    everyone = lambda s: True
    assert view.missing(3, everyone) == len(needed) and not view.ready(3, everyone)
    gone = needed[0]
    assert view.missing(3, lambda s: s != gone) == len(needed) - 1
    x = np.zeros(exp.n)
    view.add(needed[0], None, 3, x)  # a broadcast estimate: nothing else of it to come
    assert view.missing(3, everyone) == len(needed) - 1
    j = next(iter(view.out_set))
    view.add_done(needed[1], 3, [(j, 3)])  # reported a message to j that has not arrived
    assert view.missing(3, everyone) == len(needed) - 2 + 1
    view.add(needed[1], j, 3, x)
    assert view.missing(3, everyone) == len(needed) - 2
    for s in needed[2:]:
        view.add_done(s, 3, [])
    assert view.missing(3, everyone) == 0 and view.ready(3, everyone)
    assert view.missing(2, everyone) == len(needed)  # another round: nothing of it here


def test_a_broadcast_report_names_every_out_neighbour_at_its_round():
    """report_to: an "est" on a done key (an honest agent's estimate, broadcast) went to
    every out-neighbour stamped with its round; a "done" names its receivers itself."""
    from agents.net.wire import Wire, report_to
    from transport.codec import decode, encode_fields

    exp, _ = load_experiment(SCENARIOS / "mitra_cells.toml", ("run.rounds=5", "expect=[]"), None)
    wire = Wire(exp)
    x = np.zeros(exp.n)
    bcast = decode(encode_fields("est", 3, 7, {"x": x}), schema=wire.done, expected_sender=3)
    assert report_to(bcast, [1, 4, 9], exp.N) == ([1, 4, 9], [7, 7, 7])
    named = decode(encode_fields("done", 3, 7, {"x": x, "to": np.array([4.0]), "stamps": np.array([6.0])}),
                   schema=wire.done, expected_sender=3)
    assert report_to(named, [1, 4, 9], exp.N) == ([4], [6])
    assert len(encode_fields("est", 3, 7, {"x": x})) < len(encode_fields("done", 3, 7, {"x": x, "to": np.arange(8.0),
                                                                                       "stamps": np.full(8, 7.0)}))
