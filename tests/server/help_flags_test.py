"""framediffuser-server --help documents every option, and an unknown flag is
refused by name.

The option names come from the sources: the fields of struct ServerConfig
(server/server_config.h) and the names of the option table
(server/server_config.cc); they must agree, and --help must list each as
--<name>=.

Usage (ctest runs it so): python3 help_flags_test.py SERVER_BINARY SOURCE_DIR
"""
import os
import re
import subprocess
import sys
import unittest

SERVER_BINARY = None
SOURCE_DIR = None


def read(relative):
    with open(os.path.join(SOURCE_DIR, relative), encoding="utf-8") as f:
        return f.read()


def struct_fields():
    """Member names of `struct ServerConfig { ... };`."""
    body = re.search(r"struct ServerConfig \{(.*?)\n\};", read("server/server_config.h"), re.S)
    assert body, "struct ServerConfig not found in server/server_config.h"
    names = []
    for line in body.group(1).splitlines():
        code = line.split("//")[0].strip()
        match = re.match(r"^[\w:<>]+\s+(\w+)\s*(=.*)?;$", code)
        if match:
            names.append(match.group(1))
    return names


def table_names():
    """Names of the option table's rows: {"name", "Group", ...}."""
    text = read("server/server_config.cc")
    return re.findall(r'\{"([a-z0-9_]+)",\s*"([A-Z][A-Za-z ]*)",', text)


class HelpTest(unittest.TestCase):

    def run_server(self, *args):
        return subprocess.run([SERVER_BINARY, *args], stdin=subprocess.DEVNULL,
                              capture_output=True, text=True, timeout=120)

    def test_help_lists_every_option(self):
        fields = struct_fields()
        rows = table_names()
        table = [name for name, _ in rows]
        self.assertGreaterEqual(len(fields), 20, fields)
        # The table drives flags, file keys and --help: it covers the struct.
        self.assertEqual(sorted(table), sorted(fields))

        result = self.run_server("--help")
        self.assertEqual(result.returncode, 0, result.stderr)
        for name in fields:
            with self.subTest(option=name):
                self.assertRegex(result.stdout, r"(?m)^\s*--%s=" % re.escape(name))
        for flag in ("--config", "--help"):
            self.assertIn(flag, result.stdout)
        for group in sorted({group for _, group in rows}):
            self.assertRegex(result.stdout, r"(?m)^%s:$" % re.escape(group))

    def test_unknown_flag_is_named(self):
        result = self.run_server("--no_such_flag=1")
        self.assertNotEqual(result.returncode, 0)
        self.assertIn("--no_such_flag", result.stderr)

    def test_bad_value_names_the_flag(self):
        result = self.run_server("--max_batch_size=x")
        self.assertNotEqual(result.returncode, 0)
        self.assertIn("--max_batch_size", result.stderr)


def main():
    global SERVER_BINARY, SOURCE_DIR
    if len(sys.argv) < 3:
        sys.stderr.write("usage: help_flags_test.py SERVER_BINARY SOURCE_DIR [unittest args]\n")
        return 2
    SERVER_BINARY, SOURCE_DIR = sys.argv[1], sys.argv[2]
    program = unittest.main(argv=[sys.argv[0]] + sys.argv[3:], exit=False, verbosity=2)
    return 0 if program.result.wasSuccessful() else 1


if __name__ == "__main__":
    sys.exit(main())
