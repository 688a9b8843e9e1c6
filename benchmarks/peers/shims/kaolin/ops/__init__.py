# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``kaolin.ops`` (see ``kaolin``)."""
