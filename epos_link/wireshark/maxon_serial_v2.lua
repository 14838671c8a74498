-- Wireshark dissector for maxon's MAXON SERIAL V2 (EPOS4 USB & RS232 protocol).
-- Shipped with epos_link (https://pypi.org/project/epos-link); print its path with
-- `epos-link wireshark path`, install it with `epos-link wireshark install`.
--
-- Sources: EPOS4 Communication Guide (rel7290) 2.1 (op codes and message
-- layouts), 2.2.2 (frame: DLE STX OpCode Len Data CRC), 2.2.3 (CRC-CCITT over
-- 16-bit words), 2.2.4 (character stuffing: 0x90 doubled after the sync),
-- chapter 6 Table 6-21 (error codes; CiA 301 codes a gateway relays as well).
--
-- Input: pcapng with link type USER0 (147), one frame per packet as on the wire
-- (what `epos-link export` and `epos-link monitor --pcapng` write). The packet
-- direction flag says who sent it: outbound = host to device (a request),
-- inbound = device to host (an answer). An answer names the request it answers
-- (the last request before it: the device answers one request at a time,
-- guide 2.2.1) and is decoded with that request's answer layout.
-- Baseline: Wireshark 4.0 (Lua 5.2, bit32).
--
-- Object names and typed values: `epos-link wireshark install` writes
-- maxon_serial_v2.objects next to this file, generated from the EDS (the
-- shipped EPOS4 EDS, or --eds FILE): a Lua table (index << 8 | subindex) ->
-- {name, kind, size}. Not a .lua file, so Wireshark does not load it as a
-- plugin of its own. Without it, objects are shown by index only.

local maxon = Proto("maxon", "maxon EPOS4 MAXON SERIAL V2")

local DLE, STX = 0x90, 0x02

local opcodes = {
    [0x00] = "Answer",
    [0x60] = "ReadObject",
    [0x62] = "SegmentRead",
    [0x68] = "WriteObject",
    [0x69] = "InitiateSegmentedWrite",
    [0x6A] = "SegmentWrite",
    [0x70] = "SendNMTService",
    [0x81] = "InitiateSegmentedRead",
}

-- Guide Table 6-21, then CiA 301 codes relayed by the gateway (epos_link/codes.py).
local error_names = {
    [0x00000000] = "No abort",
    [0x05030000] = "Toggle error",
    [0x05040001] = "Command unknown",
    [0x05040004] = "CRC error",
    [0x06010000] = "Access error",
    [0x06010001] = "Write only error",
    [0x06010002] = "Read only error",
    [0x06020000] = "Object does not exist error",
    [0x06040041] = "PDO mapping error",
    [0x06040042] = "PDO length error",
    [0x06040043] = "General parameter error",
    [0x06040047] = "General internal incompatibility error",
    [0x06060000] = "Hardware error",
    [0x06070010] = "Service parameter error",
    [0x06090011] = "Subindex error",
    [0x06090030] = "Value range error",
    [0x08000000] = "General error",
    [0x08000020] = "Transfer or store error",
    [0x08000022] = "Wrong device state error",
    [0x0F00FFBE] = "Password error",
    [0x0F00FFBF] = "Illegal command error",
    [0x0F00FFC0] = "Wrong NMT state error",
    [0x05040000] = "SDO protocol timed out",
    [0x05040002] = "Invalid block size",
    [0x05040005] = "Out of memory",
    [0x06070012] = "Data type does not match, length too high",
    [0x06070013] = "Data type does not match, length too low",
    [0x06090031] = "Value too high",
    [0x06090032] = "Value too low",
    [0x08000021] = "Local control",
}

-- Guide Table 3-14.
local nmt_commands = {
    [0x01] = "Start remote node",
    [0x02] = "Stop remote node",
    [0x80] = "Enter pre-operational",
    [0x81] = "Reset node",
    [0x82] = "Reset communication",
}

-- The generated table of objects (see the head of this file), found next to this file.
local objects = {}
do
    local info = debug and debug.getinfo and debug.getinfo(1, "S")
    local source = info and info.source or ""
    local dir = source:sub(1, 1) == "@" and source:sub(2):match("^(.*)[/\\]") or nil
    if dir ~= nil then
        local ok, t = pcall(dofile, dir .. "/maxon_serial_v2.objects")
        if ok and type(t) == "table" then objects = t end
    end
end

-- CiA 402-2 6.4.1.4 statusword state coding (mask, value, state), as epos_link/cia402.py.
local sw_states = {
    { 0x004F, 0x0000, "not ready to switch on" },
    { 0x004F, 0x0040, "switch on disabled" },
    { 0x006F, 0x0021, "ready to switch on" },
    { 0x006F, 0x0023, "switched on" },
    { 0x006F, 0x0027, "operation enabled" },
    { 0x006F, 0x0007, "quick stop active" },
    { 0x004F, 0x000F, "fault reaction active" },
    { 0x004F, 0x0008, "fault" },
}
local sw_flags = {
    { 0x0010, "voltage enabled" }, { 0x0080, "warning" }, { 0x0200, "remote" },
    { 0x0400, "target reached" }, { 0x0800, "internal limit active" },
    { 0x8000, "position referenced" },
}

local function statusword_text(sw)
    local parts = { "no CiA 402 state" }
    for _, s in ipairs(sw_states) do
        if bit32.band(sw, s[1]) == s[2] then parts[1] = s[3]; break end
    end
    for _, fl in ipairs(sw_flags) do
        if bit32.band(sw, fl[1]) ~= 0 then parts[#parts + 1] = fl[2] end
    end
    return table.concat(parts, ", ")
end

local function object_of(index, subindex)
    return objects[index * 256 + subindex]
end

-- The value of an expedited transfer's data (up to 4 bytes, little-endian, padding
-- after the type's size ignored), as epos-link prints it: "1000 (0x000003E8)".
local function value_text(obj, range, index, subindex)
    local kind, size = obj[2], obj[3]
    if size == nil or size > 4 or range:len() < size then return nil end
    local r = range(0, size)
    local text
    if kind == "u" or kind == "i" then
        local v = kind == "u" and r:le_uint() or r:le_int()
        local masked = bit32.band(v, size == 4 and 0xFFFFFFFF or (2 ^ (8 * size) - 1))
        text = string.format("%d (0x%0" .. (2 * size) .. "X)", v, masked)
        if index == 0x6041 and subindex == 0 then
            text = text .. " [" .. statusword_text(masked) .. "]"
        end
    elseif kind == "f" and size == 4 then
        text = string.format("%g", r:le_float())
    elseif kind == "b" then
        text = r:le_uint() ~= 0 and "true" or "false"
    end
    return text
end

local f = {
    sync = ProtoField.uint16("maxon.sync", "Sync (DLE STX)", base.HEX),
    opcode = ProtoField.uint8("maxon.opcode", "OpCode", base.HEX, opcodes),
    length = ProtoField.uint8("maxon.length", "Len (words)", base.DEC),
    node = ProtoField.uint16("maxon.node", "Node ID", base.DEC),
    index = ProtoField.uint16("maxon.index", "Index", base.HEX),
    subindex = ProtoField.uint8("maxon.subindex", "Subindex", base.HEX),
    data = ProtoField.bytes("maxon.data", "Data"),
    error_code = ProtoField.uint32("maxon.error_code", "Error code", base.HEX, error_names),
    object_length = ProtoField.uint32("maxon.object_length", "Object length", base.DEC),
    write_length = ProtoField.uint32("maxon.write_length", "Length announced", base.DEC),
    segment_length = ProtoField.uint8("maxon.segment_length", "Segment length", base.DEC),
    control = ProtoField.uint8("maxon.control", "ControlByte", base.HEX),
    toggle = ProtoField.bool("maxon.toggle", "Toggle", 8, nil, 0x01),
    last = ProtoField.bool("maxon.last", "Last segment", 8, nil, 0x02),
    nmt_command = ProtoField.uint16("maxon.nmt_command", "NMT command", base.HEX, nmt_commands),
    crc = ProtoField.uint16("maxon.crc", "CRC", base.HEX),
    crc_ok = ProtoField.bool("maxon.crc_ok", "CRC good"),
    request = ProtoField.string("maxon.request", "Answer to"),
    request_in = ProtoField.framenum("maxon.request_in", "Request in frame", base.NONE, frametype.REQUEST),
    response_in = ProtoField.framenum("maxon.response_in", "Answer in frame", base.NONE, frametype.RESPONSE),
    time = ProtoField.double("maxon.time", "Time since request (s)"),
    object = ProtoField.string("maxon.object", "Object"),
    value = ProtoField.string("maxon.value", "Value"),
}
maxon.fields = f

local ef = {
    crc = ProtoExpert.new("maxon.crc_bad", "CRC mismatch", expert.group.CHECKSUM, expert.severity.ERROR),
    stuffing = ProtoExpert.new("maxon.stuffing_bad", "Stuffing error: DLE followed by neither DLE nor STX",
                               expert.group.MALFORMED, expert.severity.ERROR),
    short = ProtoExpert.new("maxon.short", "Frame shorter than its Len field", expert.group.MALFORMED,
                            expert.severity.ERROR),
    not_frame = ProtoExpert.new("maxon.not_frame", "Bytes that are not a frame (no DLE STX)",
                                expert.group.MALFORMED, expert.severity.WARN),
    device_error = ProtoExpert.new("maxon.device_error", "The device answered with an error code",
                                   expert.group.RESPONSE_CODE, expert.severity.WARN),
}
maxon.experts = { ef.crc, ef.stuffing, ef.short, ef.not_frame, ef.device_error }

-- Pairing state, rebuilt on every (re)dissection of the capture.
local last_request   -- {frame=, opcode=, node=, index=, subindex=, time=}
local request_of = {}  -- answer frame number -> request record
local answer_of = {}   -- request frame number -> answer frame number
local transfer = nil   -- object of the segmented transfer in progress
local transfer_of = {} -- frame number -> object of its segmented transfer

function maxon.init()
    last_request = nil
    request_of = {}
    answer_of = {}
    transfer = nil
    transfer_of = {}
end

-- CRC-16/XMODEM (poly 0x1021, init 0) of the words, each high byte first
-- (guide 2.2.3: the first word is Len << 8 | OpCode, data words as received).
local function crc_ccitt(bytes)
    local crc = 0
    for i = 1, #bytes do
        crc = bit32.bxor(crc, bit32.lshift(bytes[i], 8))
        for _ = 1, 8 do
            if bit32.band(crc, 0x8000) ~= 0 then
                crc = bit32.band(bit32.bxor(bit32.lshift(crc, 1), 0x1021), 0xFFFF)
            else
                crc = bit32.band(bit32.lshift(crc, 1), 0xFFFF)
            end
        end
    end
    return crc
end

-- Undo the stuffing of everything after the sync. Returns a ByteArray and
-- the offset (in the packet) of the first stuffing error, or nil.
local function unstuff(tvb, from)
    local out = ByteArray.new()
    local bad = nil
    local i = from
    local n = tvb:len()
    local count = 0
    while i < n do
        local b = tvb(i, 1):uint()
        if b == DLE and i + 1 < n and tvb(i + 1, 1):uint() == DLE then
            i = i + 2
        elseif b == DLE and bad == nil then
            bad = i
            i = i + 1
        else
            i = i + 1
        end
        count = count + 1
        out:set_size(count)
        out:set_index(count - 1, b)
    end
    return out, bad
end

local function le32(t, off) return t(off, 4):le_uint() end

local function address_text(node, index, subindex)
    return string.format("node %d 0x%04X/0x%02X", node, index, subindex)
end

-- The object's name (and the value in ``range``, if given) from the generated table;
-- returns the text for the Info column.
local function add_object(tree, index, subindex, range)
    local obj = object_of(index, subindex)
    if obj == nil then return "" end
    tree:add(f.object, obj[1]):set_generated()
    local text = " " .. obj[1]
    if range ~= nil then
        local v = value_text(obj, range, index, subindex)
        if v ~= nil then
            tree:add(f.value, v):set_generated()
            text = text .. " = " .. v
        end
    end
    return text
end

local function add_address(tree, body, off)
    tree:add(f.node, body(off, 1))
    tree:add_le(f.index, body(off + 1, 2))
    tree:add(f.subindex, body(off + 3, 1))
    return body(off, 1):uint(), body(off + 1, 2):le_uint(), body(off + 3, 1):uint()
end

local function dissect_request(opcode, data, tree, pinfo, info)
    local n = data:len()
    local rec = { frame = pinfo.number, opcode = opcode, time = pinfo.rel_ts }
    if (opcode == 0x60 or opcode == 0x81 or opcode == 0x68 or opcode == 0x69) and n >= 4 then
        rec.node, rec.index, rec.subindex = add_address(tree, data, 0)
        info = info .. " " .. address_text(rec.node, rec.index, rec.subindex)
        if opcode == 0x68 and n >= 8 then
            tree:add(f.data, data(4, 4))
            info = info .. add_object(tree, rec.index, rec.subindex, data(4, 4))
                .. " data " .. tostring(data(4, 4):bytes())
        else
            info = info .. add_object(tree, rec.index, rec.subindex, nil)
        end
        if opcode == 0x69 and n >= 8 then
            tree:add_le(f.write_length, data(4, 4))
        end
    elseif opcode == 0x62 and n >= 1 then
        tree:add(f.control, data(0, 1))
        tree:add(f.toggle, data(0, 1))
        info = info .. string.format(" toggle=%d", bit32.band(data(0, 1):uint(), 1))
    elseif opcode == 0x6A and n >= 2 then
        local len = data(0, 1):uint()
        tree:add(f.segment_length, data(0, 1))
        tree:add(f.control, data(1, 1))
        tree:add(f.toggle, data(1, 1))
        tree:add(f.last, data(1, 1))
        if len > 0 and 2 + len <= n then tree:add(f.data, data(2, len)) end
    elseif opcode == 0x70 and n >= 4 then
        tree:add_le(f.node, data(0, 2))
        tree:add_le(f.nmt_command, data(2, 2))
        local cs = data(2, 2):le_uint()
        info = info .. string.format(" node %d %s", data(0, 2):le_uint(), nmt_commands[cs] or string.format("0x%02X", cs))
    elseif n > 0 then
        tree:add(f.data, data(0, n))
    end
    return rec, info
end

local function dissect_answer(req, data, tree, pinfo, info)
    local n = data:len()
    if n < 4 then
        if n > 0 then tree:add(f.data, data(0, n)) end
        return info
    end
    local code = le32(data, 0)
    local item = tree:add_le(f.error_code, data(0, 4))
    if code ~= 0 then item:add_proto_expert_info(ef.device_error) end
    local obj = nil
    if req ~= nil then
        local name = opcodes[req.opcode] or string.format("0x%02X", req.opcode)
        local r = tree:add(f.request, name):set_generated()
        tree:add(f.request_in, req.frame):set_generated()
        tree:add(f.time, pinfo.rel_ts - req.time):set_generated()
        info = "Answer to " .. name
        if req.index ~= nil then
            obj = req
        else
            obj = transfer_of[pinfo.number]
        end
        if obj ~= nil then
            tree:add(f.node, obj.node):set_generated()
            tree:add(f.index, obj.index):set_generated()
            tree:add(f.subindex, obj.subindex):set_generated()
            info = info .. " " .. address_text(obj.node, obj.index, obj.subindex)
            -- A ReadObject answer carries the value (guide 2.1.1.1): typed by the EDS.
            local value = (req.opcode == 0x60 and code == 0 and n >= 8) and data(4, 4) or nil
            info = info .. add_object(tree, obj.index, obj.subindex, value)
        end
    end
    info = info .. (code == 0 and ": ok" or string.format(": 0x%08X %s", code, error_names[code] or "unknown error"))
    if code ~= 0 and n == 4 then return info end
    local op = req and req.opcode or nil
    if op == 0x60 and n >= 8 then
        tree:add(f.data, data(4, 4))
        info = info .. " data " .. tostring(data(4, 4):bytes())
    elseif op == 0x81 and n >= 9 then
        tree:add_le(f.object_length, data(4, 4))
        tree:add(f.segment_length, data(8, 1))
        local len = data(8, 1):uint()
        if len > 0 and 9 + len <= n then tree:add(f.data, data(9, len)) end
        info = info .. string.format(" object length %d", le32(data, 4))
    elseif op == 0x62 and n >= 6 then
        tree:add(f.segment_length, data(4, 1))
        tree:add(f.control, data(5, 1))
        tree:add(f.toggle, data(5, 1))
        tree:add(f.last, data(5, 1))
        local len = data(4, 1):uint()
        if len > 0 and 6 + len <= n then tree:add(f.data, data(6, len)) end
    elseif op == 0x6A and n >= 6 then
        tree:add(f.segment_length, data(4, 1))
        tree:add(f.control, data(5, 1))
        tree:add(f.toggle, data(5, 1))
    elseif n > 4 then
        tree:add(f.data, data(4, n - 4))
    end
    return info
end

function maxon.dissector(tvb, pinfo, tree)
    local n = tvb:len()
    if n == 0 then return 0 end
    pinfo.cols.protocol = "MAXON"
    local root = tree:add(maxon, tvb(), "MAXON SERIAL V2")
    local outbound = pinfo.p2p_dir == 0
    local inbound = pinfo.p2p_dir == 1
    if n < 4 or tvb(0, 1):uint() ~= DLE or tvb(1, 1):uint() ~= STX then
        root:add(f.data, tvb(0, n))
        root:add_proto_expert_info(ef.not_frame)
        pinfo.cols.info = string.format("Not a frame (%d bytes)", n)
        return n
    end
    root:add(f.sync, tvb(0, 2))
    local bytes, bad = unstuff(tvb, 2)
    local body = bytes:tvb("Unstuffed frame")
    if bad ~= nil then
        root:add_proto_expert_info(ef.stuffing, string.format("Stuffing error at byte %d", bad))
    end
    local opcode = body(0, 1):uint()
    local words = body:len() > 1 and body(1, 1):uint() or 0
    root:add(f.opcode, body(0, 1))
    if body:len() > 1 then root:add(f.length, body(1, 1)) end
    local want = 2 + 2 * words + 2
    if body:len() < want then
        root:add_proto_expert_info(ef.short)
        pinfo.cols.info = string.format("%s (truncated)", opcodes[opcode] or string.format("0x%02X", opcode))
        return n
    end
    local data = body(2, 2 * words):tvb()
    local received = body(2 + 2 * words, 2):le_uint()
    -- The CRC sees each word high byte first: Len then OpCode, then each data word swapped.
    local words_be = { words, opcode }
    for i = 0, 2 * words - 1, 2 do
        words_be[#words_be + 1] = body(3 + i, 1):uint()
        words_be[#words_be + 1] = body(2 + i, 1):uint()
    end
    local computed = crc_ccitt(words_be)
    local answer = opcode == 0x00 or inbound
    local info = opcodes[opcode] or string.format("Unknown op code 0x%02X", opcode)
    if answer then
        local req = nil
        if not pinfo.visited then
            if last_request ~= nil then
                request_of[pinfo.number] = last_request
                answer_of[last_request.frame] = pinfo.number
                if last_request.opcode == 0x62 or last_request.opcode == 0x6A then
                    transfer_of[pinfo.number] = transfer
                end
            end
            last_request = nil
        end
        req = request_of[pinfo.number]
        info = dissect_answer(req, data, root, pinfo, info)
    else
        local rec
        rec, info = dissect_request(opcode, data, root, pinfo, info)
        if not pinfo.visited then
            last_request = rec
            if opcode == 0x81 or opcode == 0x69 then
                transfer = rec
            elseif opcode == 0x62 or opcode == 0x6A then
                transfer_of[pinfo.number] = transfer
            else
                transfer = nil
            end
        end
        local obj = transfer_of[pinfo.number]
        if (opcode == 0x62 or opcode == 0x6A) and obj ~= nil then
            root:add(f.node, obj.node):set_generated()
            root:add(f.index, obj.index):set_generated()
            root:add(f.subindex, obj.subindex):set_generated()
            info = info .. " " .. address_text(obj.node, obj.index, obj.subindex)
        end
        if answer_of[pinfo.number] ~= nil then
            root:add(f.response_in, answer_of[pinfo.number]):set_generated()
        end
    end
    local crc_item = root:add_le(f.crc, body(2 + 2 * words, 2))
    local ok = received == computed
    root:add(f.crc_ok, ok):set_generated()
    if not ok then
        crc_item:append_text(string.format(" [computed 0x%04X]", computed))
        crc_item:add_proto_expert_info(ef.crc)
        info = info .. " [CRC BAD]"
    end
    if bad ~= nil then info = info .. " [STUFFING ERROR]" end
    pinfo.cols.info = info
    if outbound then pinfo.cols.src = "host"; pinfo.cols.dst = "EPOS4" end
    if inbound then pinfo.cols.src = "EPOS4"; pinfo.cols.dst = "host" end
    return n
end

DissectorTable.get("wtap_encap"):add(wtap.USER0, maxon)
