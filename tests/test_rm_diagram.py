"""DOT and Mermaid diagrams of the event-ordered RM (paper Figure 2)."""
import re

import pytest

from rm_torchrl.errors import RMError
from rm_torchrl.rm import EventOrderedRM
from rm_torchrl.rm.diagram import to_dot, to_mermaid

DOT_NODE = re.compile(r'^\s*(s\d+) \[label="((?:[^"\\]|\\.)*)"(.*)\];$')
DOT_EDGE = re.compile(r'^\s*(s\d+) -> (s\d+) \[label="((?:[^"\\]|\\.)*)"\];$')
MM_NODE = re.compile(r'^\s*(s\d+)\("([^"]*)"\)$')
MM_EDGE = re.compile(r'^\s*(s\d+) -->\|"([^"]*)"\| (s\d+)$')


def parse_dot(text):
    nodes, edges = {}, set()
    for line in text.splitlines():
        if m := DOT_NODE.match(line):
            nodes[m[1]] = (m[2], "filled" in m[3])
        elif m := DOT_EDGE.match(line):
            edges.add((nodes[m[1]][0], m[3], nodes[m[2]][0]))
    return nodes, edges


def parse_mermaid(text):
    nodes, edges, terminal = {}, set(), set()
    for line in text.splitlines():
        if m := MM_NODE.match(line):
            nodes[m[1]] = m[2]
        elif m := MM_EDGE.match(line):
            edges.add((nodes[m[1]], m[2], nodes[m[3]]))
        elif line.strip().startswith("class "):
            terminal |= {nodes[i] for i in line.split()[1].split(",")}
    return nodes, edges, terminal


def expected_edges(n):
    """Figure 2 from Definition 3.1: an unseen event fills the first empty slot."""
    names = [f"e{k}" for k in range(1, n + 1)]
    edges = set()

    def walk(prefix):
        for e in names:
            if e not in prefix:
                src = "(" + ", ".join(list(prefix) + ["e0"] * (n - len(prefix))) + ")"
                nxt = prefix + (e,)
                dst = "(" + ", ".join(list(nxt) + ["e0"] * (n - len(nxt))) + ")"
                edges.add((src, e, dst))
                walk(nxt)

    walk(())
    return edges


def test_dot_n3_matches_figure_2():
    text = to_dot(EventOrderedRM(3))
    assert text.startswith("digraph") and "rankdir=LR;" in text
    nodes, edges = parse_dot(text)
    assert len(nodes) == 16
    # 3 + 3*2 + 6*1 edges; no self-loops
    assert len(edges) == 15 and text.count("->") == 16  # plus the start marker
    assert edges == expected_edges(3)
    assert ("(e1, e0, e0)", "e2", "(e1, e2, e0)") in edges
    assert all(src != dst for src, _, dst in edges)
    terminal = {label for label, filled in nodes.values() if filled}
    assert len(terminal) == 6 and all("e0" not in t for t in terminal)
    assert "fillcolor" in text and 'label="start"' in text
    assert "start -> s0;" in text and nodes["s0"][0] == "(e0, e0, e0)"


def test_out_degree_is_n_minus_filled_slots():
    rm = EventOrderedRM(4)
    _, edges = parse_dot(to_dot(rm))
    out = {}
    for src, _, _ in edges:
        out[src] = out.get(src, 0) + 1
    for label in (rm.state_name(s) for s in rm.states.tolist()):
        filled = 4 - label.count("e0")
        assert out.get(label, 0) == 4 - filled
    assert len(edges) == rm.num_states - 1  # a tree: every state but the start has one parent


def test_mermaid_n3_same_content():
    text = to_mermaid(EventOrderedRM(3))
    assert text.splitlines()[0] == "flowchart LR"
    nodes, edges, terminal = parse_mermaid(text)
    assert len(nodes) == 16 and edges == expected_edges(3)
    assert len(terminal) == 6 and all("e0" not in t for t in terminal)
    assert "start" in text and "--> s0" in text and "classDef terminal fill:" in text
    # ids are safe identifiers
    assert all(re.fullmatch(r"s\d+", i) for i in nodes)


def test_names_with_spaces_dots_and_quotes_are_escaped():
    rm = EventOrderedRM(["light switch", "door_0.2", 'say "hi"', "a;b#c"])
    dot = to_dot(rm)
    nodes, edges = parse_dot(dot)
    assert ("(e0, e0, e0, e0)", "light switch", "(light switch, e0, e0, e0)") in edges
    assert ("(e0, e0, e0, e0)", "door_0.2", "(door_0.2, e0, e0, e0)") in edges
    assert ("(e0, e0, e0, e0)", 'say \\"hi\\"', '(say \\"hi\\", e0, e0, e0)') in edges
    # every statement is on one line and ids never contain the names
    for line in dot.splitlines()[1:-1]:
        assert line.rstrip().endswith(";")
        assert re.match(r"\s*(s\d+|start)\b", line) or "=" in line

    mm = to_mermaid(rm)
    nodes, edges, _ = parse_mermaid(mm)
    assert len(nodes) == rm.num_states
    assert ("(e0, e0, e0, e0)", "light switch", "(light switch, e0, e0, e0)") in edges
    assert ("(e0, e0, e0, e0)", "door_0.2", "(door_0.2, e0, e0, e0)") in edges
    assert ("(e0, e0, e0, e0)", "say #34;hi#34;", "(say #34;hi#34;, e0, e0, e0)") in edges
    assert ("(e0, e0, e0, e0)", "a#59;b#35;c", "(a#59;b#35;c, e0, e0, e0)") in edges
    assert all(re.fullmatch(r"s\d+", i) for i in nodes)


def test_single_event():
    nodes, edges = parse_dot(to_dot(EventOrderedRM(["go"])))
    assert nodes == {"s0": ("(e0)", False), "s1": ("(go)", True)}
    assert edges == {("(e0)", "go", "(go)")}


@pytest.mark.parametrize("writer", [to_dot, to_mermaid])
def test_too_many_states(writer):
    rm = EventOrderedRM(3)
    with pytest.raises(RMError, match="16 states"):
        writer(rm, max_states=15)
    assert writer(rm, max_states=16)
    # refused before the n! state table is built
    with pytest.raises(RMError, match="9864101 states"):
        writer(EventOrderedRM(10))
    with pytest.raises(RMError, match="max_states"):
        writer(rm, max_states=0)


# --- one event order's path (issue 19: rmrl rm-graph --order) ------------------------------

@pytest.mark.parametrize("order", [["e2", "e3", "e1"], ["e3", "e1"]])
def test_an_order_draws_only_its_path_with_the_full_graphs_ids(order):
    rm = EventOrderedRM(3)
    full_nodes, full_edges = parse_dot(to_dot(rm))
    nodes, edges = parse_dot(to_dot(rm, order=order))
    assert len(nodes) == len(order) + 1 and len(edges) == len(order)
    assert set(nodes.items()) <= set(full_nodes.items())  # same ids, labels and colours as the whole RM
    assert edges <= full_edges and edges == set(zip(
        ["(e0, e0, e0)", *(f"({', '.join(order[:i] + ['e0'] * (3 - i))})" for i in range(1, len(order)))],
        order, [f"({', '.join(order[:i] + ['e0'] * (3 - i))})" for i in range(1, len(order) + 1)]))
    terminal = [label for label, filled in nodes.values() if filled]
    assert terminal == (["(e2, e3, e1)"] if len(order) == 3 else [])
    mm_nodes, mm_edges, mm_terminal = parse_mermaid(to_mermaid(rm, order=order))
    assert set(mm_nodes.values()) == {label for label, _ in nodes.values()} and mm_edges == edges
    assert mm_terminal == set(terminal)


def test_a_path_is_drawn_however_many_states_the_rm_has():
    rm = EventOrderedRM(10)  # 9,864,101 states: the whole RM is refused, one path is 11 nodes
    nodes, edges = parse_dot(to_dot(rm, order=[f"e{k}" for k in range(10, 0, -1)]))
    assert len(nodes) == 11 and len(edges) == 10


@pytest.mark.parametrize("order, message", [
    (["e1", "x", "e2", "y", "x"], r"^the order names events the spec does not have: x, y \(its events: e1, e2, e3\)$"),
    (["e1", "e2", "e1"], r"^the order repeats e1: each event occurs once on an RM path$"),
    (["e1", "", "e2"], r"^an order is one or more event names separated by commas, got 'e1,,e2'$"),
    ([], r"^an order is one or more event names"),
])
def test_a_bad_order_is_one_line_naming_the_events(order, message):
    for writer in (to_dot, to_mermaid):
        with pytest.raises(RMError, match=message):
            writer(EventOrderedRM(3), order=order)
